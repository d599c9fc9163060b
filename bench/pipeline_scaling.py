"""Scaling of the pipeline's batch stages with dask workers: run validate .. shard on one simulated capture with
a LocalCluster of 1 and of 2 single-threaded worker processes (fresh work directories, cluster start-up not
timed) and print per-stage seconds and speed-ups as a markdown table (and JSON with --json).

    python bench/pipeline_scaling.py --preset small --out /tmp/lightstage-bench
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import sys
import time
from pathlib import Path

from lightstage.pipelines.cluster import open_executor
from lightstage.pipelines.config import load_pipeline_config
from lightstage.pipelines.runner import run_pipeline
from lightstage.pipelines.stages import BATCH_STAGES
from lightstage.workdir import WorkDir


def simulated_capture(out: Path, preset: str, seed: int) -> Path:
    """Simulate the capture once (reused by later runs of the benchmark)."""
    from lightstage.simulator.simulate import simulate_capture

    capture = out / f"capture-{preset}-{seed}"
    marker = capture / ".bench-complete"
    if marker.is_file():
        return capture
    if capture.exists():
        shutil.rmtree(capture)
    t0 = time.perf_counter()
    simulate_capture(capture, preset=preset, seed=seed)
    print(f"simulated {preset} in {time.perf_counter() - t0:.0f} s", file=sys.stderr)
    marker.write_text("ok\n")
    return capture


def run_once(capture: Path, work_root: Path, workers: int, to_stage: str, config_path: str | None) -> dict:
    """Batch stages on a fresh work directory with `workers` worker processes; seconds per stage."""
    if work_root.exists():
        shutil.rmtree(work_root)
    config = load_pipeline_config(config_path or "default").with_cluster(workers=workers, dashboard="")
    with open_executor(config.cluster, verbose=False) as executor:
        t0 = time.perf_counter()
        results = run_pipeline(
            WorkDir.at(work_root),
            config,
            capture=capture,
            to_stage=to_stage,
            executor=executor,
            progress=False,
            log=lambda m: print(f"  [{workers} worker(s)] {m}", file=sys.stderr),
        )
        total = time.perf_counter() - t0
    return {"total": total, "stages": {r.stage: r.seconds for r in results}}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--preset", default="small", help="simulator preset (default small)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--capture", type=Path, help="use this capture instead of simulating one")
    parser.add_argument("--out", type=Path, default=Path("/tmp/lightstage-bench-pipeline"))
    parser.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    parser.add_argument(
        "--to", default=BATCH_STAGES[-1], choices=BATCH_STAGES, help="last stage (default shard)"
    )
    parser.add_argument("--config", help="pipeline config (stage parameters)")
    parser.add_argument("--json", type=Path, help="also write the results here")
    args = parser.parse_args(argv)

    args.out.mkdir(parents=True, exist_ok=True)
    capture = args.capture or simulated_capture(args.out, args.preset, args.seed)
    runs = {}
    for n in args.workers:
        runs[n] = run_once(capture, args.out / f"work-{n}", n, args.to, args.config)
        print(f"{n} worker(s): {runs[n]['total']:.1f} s", file=sys.stderr)

    base = runs[args.workers[0]]
    stages = list(base["stages"])
    head = "| stage | " + " | ".join(f"{n} worker(s) s" for n in args.workers) + " | speed-up |"
    print(
        f"\ncapture {capture} ({args.preset}); {platform.node()}, {os.cpu_count()} CPUs, load {os.getloadavg()}"
    )
    print(head)
    print("|" + "---|" * (len(args.workers) + 2))
    last = args.workers[-1]
    for stage in [*stages, "total"]:
        vals = [
            runs[n]["stages"].get(stage, 0.0) if stage != "total" else runs[n]["total"] for n in args.workers
        ]
        speed = vals[0] / vals[-1] if vals[-1] > 0 else float("nan")
        print(f"| {stage} | " + " | ".join(f"{v:.1f}" for v in vals) + f" | {speed:.2f}x |")
    if args.json:
        args.json.write_text(json.dumps({"capture": str(capture), "runs": runs, "last": last}, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
