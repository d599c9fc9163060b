"""Subcommands of this package; each handler imports its heavy dependencies lazily."""

from __future__ import annotations

import argparse
from pathlib import Path

from lightstage.cli_args import add_quiet


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add `preprocess`."""
    p = subparsers.add_parser(
        "preprocess",
        help="4x HDR downscale, per-view statistics, masks/zones and flare rejects of a raw capture",
        description=(
            "Preprocess a raw capture into WORK/preprocess: 4x area-downscaled half EXR frames (R, G, B, S), "
            "per-view statistics, mean/well-lit images, masks, zone maps, overlays and flare scores. "
            "Resumable: rerun the same command after an interruption."
        ),
    )
    p.add_argument("capture", type=Path, help="raw capture directory (stage.yaml, capture.yaml, frames)")
    p.add_argument("--work", type=Path, required=True, help="work directory to write into")
    p.add_argument(
        "--config", type=Path, help="YAML with preprocess settings (a mapping, or a 'preprocess:' section)"
    )
    p.add_argument(
        "--workers", type=int, default=0, help="dask worker processes (0: run in this process; default 0)"
    )
    p.add_argument("--scheduler", help="address of an existing dask scheduler (instead of --workers)")
    p.add_argument(
        "--threads", type=int, default=0, help="library threads when running in-process (0: all cores)"
    )
    add_quiet(p)
    p.set_defaults(func=_preprocess)


def _load_config(path: Path | None):  # noqa: ANN202 - PreprocessConfig, imported lazily

    from lightstage.config import read_yaml
    from lightstage.preprocess.config import PreprocessConfig

    if path is None:
        return PreprocessConfig()
    data = read_yaml(path, "preprocess config") or {}
    if isinstance(data, dict) and isinstance(data.get("preprocess"), dict):
        data = data["preprocess"]
    return PreprocessConfig.from_dict(data, source=str(path))


def _preprocess(args: argparse.Namespace) -> int:
    import json
    import os

    from lightstage.capture.layout import open_capture
    from lightstage.errors import LightstageError
    from lightstage.preprocess.run import run_preprocess
    from lightstage.threads import set_library_threads
    from lightstage.workdir import WorkDir

    config = _load_config(args.config)
    capture = open_capture(args.capture)  # validates stage.yaml / capture.yaml before anything is written
    if args.workers < 0:
        raise LightstageError(f"--workers: expected an integer >= 0, got {args.workers}")
    work = WorkDir.at(args.work)
    work.link_capture(capture.root)
    progress = not args.quiet
    if args.workers or args.scheduler:
        from lightstage.dask_executor import dask_executor

        with dask_executor(args.scheduler, max(args.workers, 1), dashboard="", verbose=progress) as executor:
            summary = run_preprocess(work, config, executor, progress=progress)
    else:
        set_library_threads(args.threads or os.cpu_count() or 1)
        summary = run_preprocess(work, config, progress=progress)
    print(json.dumps(summary, indent=2))
    return 0
