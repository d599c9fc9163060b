"""Subcommands of the pipeline package: `run` (the whole job), `demo` (simulate + run + report) and
`config show` (the effective pipeline config)."""

from __future__ import annotations

import argparse
from pathlib import Path

from lightstage.cli_args import add_quiet

# pipelines.stages.STAGE_ORDER, spelled out so `lightstage --help` need not import every stage (a test checks)
STAGES = ("validate", "preprocess", "calibrate", "split", "bounds", "shard", "train", "eval")


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add `run`, `demo` and `config`."""
    run = subparsers.add_parser(
        "run",
        help="run the whole pipeline (validate .. eval) as resumable batch work (dask or in-process)",
        description=(
            "Run validate -> preprocess -> calibrate -> split -> bounds -> shard on dask, then train -> eval. "
            "Finished stages whose config and inputs are unchanged are skipped; a killed run resumes. "
            "Give either a pipeline config (CONFIG.yaml with capture: and work:) or CAPTURE --work WORK."
        ),
    )
    run.add_argument(
        "target",
        type=Path,
        help="a pipeline config (.yaml), a raw capture directory, or a work directory (WORK/capture.txt names its capture; an imported one uses WORK/import.yaml)",
    )
    run.add_argument("--work", type=Path, help="work directory (overrides the config's work:)")
    run.add_argument(
        "--config", type=Path, help="pipeline config when TARGET is a capture (default: built-in)"
    )
    run.add_argument("--scheduler", help="address of an existing dask scheduler, e.g. tcp://HOST:8786")
    run.add_argument(
        "--workers",
        type=int,
        help="worker processes of the local cluster (default 2; 0 = no dask, run in this process)",
    )
    run.add_argument(
        "--from", dest="from_stage", choices=STAGES, help="rerun this stage and everything after it"
    )
    run.add_argument("--only", choices=STAGES, help="run only this stage (even if up to date)")
    run.add_argument("--to", dest="to_stage", choices=STAGES, help="stop after this stage (e.g. --to shard)")
    run.add_argument(
        "--clean", action="store_true", help="with --from/--only: remove the forced stages' outputs first"
    )
    add_quiet(run)
    run.set_defaults(func=_run, resolve_work=_run_work)

    demo = subparsers.add_parser(
        "demo",
        help="simulate a small capture, run the whole pipeline on it and write a report",
        description="Simulate a capture, run every stage with the `cpu` training config, write WORK/report.md.",
    )
    demo.add_argument(
        "--work", type=Path, default=Path("demo-work"), help="work directory (default demo-work)"
    )
    demo.add_argument("--config", type=Path, help="pipeline config (default: built-in demo)")
    demo.add_argument("--preset", help="simulate this preset in full instead of the demo config's capture")
    demo.add_argument("--seed", type=int, help="simulator seed (default: the demo config's)")
    demo.add_argument("--workers", type=int, help="worker processes of the local cluster")
    demo.add_argument("--scheduler", help="address of an existing dask scheduler")
    add_quiet(demo)
    demo.set_defaults(func=_demo)

    cfg = subparsers.add_parser("config", help="show the effective pipeline config")
    cfg_sub = cfg.add_subparsers(dest="config_command", metavar="ACTION", required=True)
    show = cfg_sub.add_parser("show", help="print the effective config (defaults filled in) as YAML")
    show.add_argument("config", nargs="?", help="pipeline config file or built-in name (default: default)")
    show.set_defaults(func=_config_show)
    js = cfg_sub.add_parser(
        "job-script", help="print the batch script of one job of dask workers (cluster kind slurm or pbs)"
    )
    js.add_argument("config", help="pipeline config file with cluster: {kind: slurm|pbs, ...}")
    js.set_defaults(func=_config_job_script)


def _run_target(args: argparse.Namespace):  # noqa: ANN202 - (PipelineConfig, capture), imported lazily
    """The pipeline config and capture of `run TARGET`: TARGET is a config file, a capture directory, or a work
    directory that names its capture."""
    from lightstage.errors import LightstageError
    from lightstage.pipelines.config import load_pipeline_config

    target: Path = args.target
    if target.is_dir() and (target / "capture.txt").is_file() and not (target / "stage.yaml").is_file():
        return _work_dir_target(args, target)
    if target.is_file() or target.suffix in (".yaml", ".yml"):
        if args.config:
            raise LightstageError("give the config either as TARGET or with --config, not both")
        config = load_pipeline_config(target)
        return config, config.capture
    return load_pipeline_config(args.config), str(target)


def _work_dir_target(args: argparse.Namespace, work: Path):  # noqa: ANN202 - as _run_target
    """`run WORK`: a work directory names its capture (WORK/capture.txt); an imported one also its pipeline
    config (WORK/import.yaml, written by `lightstage import`), used unless --config is given."""
    import dataclasses

    from lightstage.pipelines.config import load_pipeline_config
    from lightstage.workdir import WorkDir

    imported = work / "import.yaml"
    config = load_pipeline_config(args.config or (imported if imported.is_file() else None))
    capture = str(WorkDir.at(work).capture_path())
    return dataclasses.replace(config, work=str(work), capture=capture), capture


def _run_work(args: argparse.Namespace) -> Path | None:
    """The work directory of `run` without --work: the config's `work:` (the CLI locks it before _run)."""
    config, _ = _run_target(args)
    return Path(config.work) if config.work else None


def _run(args: argparse.Namespace) -> int:
    from lightstage.errors import LightstageError
    from lightstage.pipelines.runner import run_pipeline
    from lightstage.workdir import WorkDir

    target: Path = args.target
    config, capture = _run_target(args)
    work = args.work or (Path(config.work) if config.work else None)
    if work is None:
        raise LightstageError("no work directory: pass --work WORK or set work: in the config")
    if capture is None and not WorkDir.at(work).capture_pointer.is_file():
        raise LightstageError(f"{target}: no capture: set capture: in the config or run CAPTURE --work WORK")
    config = config.with_cluster(scheduler=args.scheduler, workers=args.workers)
    results = run_pipeline(
        WorkDir.at(work),
        config,
        capture=capture,
        from_stage=args.from_stage,
        only=args.only,
        to_stage=args.to_stage,
        clean=args.clean,
        progress=not args.quiet,
    )
    print(f"pipeline finished in {work} (records in {WorkDir.at(work).root / 'reports'}):")
    for r in results:
        took = f"{r.seconds:8.1f} s" if r.status == "ran" else " " * 10
        print(f"  {r.stage:<10} {r.status:<8} {took}  {r.reason}")
    return 0


def _demo(args: argparse.Namespace) -> int:
    from lightstage.pipelines.demo import run_demo

    run_demo(
        args.work,
        config_path=args.config,
        preset=args.preset,
        seed=args.seed,
        workers=args.workers,
        scheduler=args.scheduler,
        progress=not args.quiet,
    )
    return 0


def _config_job_script(args: argparse.Namespace) -> int:
    from lightstage.errors import LightstageError
    from lightstage.pipelines.cluster import job_script
    from lightstage.pipelines.config import load_pipeline_config

    config = load_pipeline_config(args.config)
    if config.cluster.kind == "local":
        raise LightstageError(f"{config.source}: cluster.kind is local; a job script needs kind slurm or pbs")
    print(job_script(config.cluster), end="")
    return 0


def _config_show(args: argparse.Namespace) -> int:
    from lightstage.pipelines.config import dump_yaml, load_pipeline_config

    config = load_pipeline_config(args.config)
    print(f"# effective pipeline config from {config.source}")
    print(dump_yaml(config.effective()), end="")
    return 0
