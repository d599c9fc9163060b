"""The scale bench: the batch stages (validate -> preprocess -> calibrate -> split -> bounds -> shard) on a
paper-geometry capture (`paper-512`: 20 cameras, 9 groups, 331 lights at a raw 512 x 344; all 59,580 frames, or a
subset with --groups/--lights) on a dask cluster whose scheduler and workers are separate processes
(`dask scheduler` / `dask worker`, as on real machines; tests/test_cluster_resume.py's DaskProcesses).

Per stage it records the wall time, the work time (the scheduler's summed task compute time), the orchestration
overhead per frame ((wall x workers - work) / frames), the number of tasks, and at the end the peak RSS of the
scheduler, the workers and this client (VmHWM) and the sizes of the records and manifests. --kill-after N kills
the scheduler once N processed frames exist, restarts everything, reruns, and compares the tree with an
uninterrupted run's (bench/tree_hash.py). Results: docs/benchmarks.md.

    python bench/scale_bench.py OUT [--groups 0-8] [--lights 42,297] [--workers 2] [--kill-after 200] [--json F]
                                    [--config CONFIG.yaml]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import shutil
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "tests"))
sys.path.insert(0, str(REPO / "bench"))


def vm_hwm_mb(pid: int) -> float:
    """Peak RSS (VmHWM) of a live process in MB."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def scheduler_counts(client) -> dict[str, list[float]]:
    """{task prefix: [tasks finished or failed, summed compute seconds]} from the scheduler (its per-prefix
    counts of transitions into each state accumulate: a task enters `memory` or `erred` once per run of it)."""

    def counts(dask_scheduler) -> dict:
        return {
            name: [
                tp.state_counts.get("memory", 0) + tp.state_counts.get("erred", 0),
                float(tp.all_durations.get("compute", 0.0)),
            ]
            for name, tp in dask_scheduler.task_prefixes.items()
        }

    return client.run_on_scheduler(counts)


def frames_of(work: Path) -> int:
    """Processed frames on disk."""
    frames = work / "preprocess" / "frames"
    return sum(1 for _ in frames.rglob("*.exr")) if frames.is_dir() else 0


def run_stages(capture: Path, work: Path, address: str, workers: int, config_path: str) -> list[dict]:
    """Each batch stage alone (`--only`) on the cluster at `address`; per-stage figures."""
    from distributed import Client

    from lightstage.pipelines.cluster import open_executor
    from lightstage.pipelines.config import load_pipeline_config
    from lightstage.pipelines.runner import run_pipeline
    from lightstage.pipelines.stages import BATCH_STAGES
    from lightstage.workdir import WorkDir

    config = load_pipeline_config(config_path).with_cluster(scheduler=address)
    rows = []
    with Client(address, timeout="30s") as stats, open_executor(config.cluster, verbose=False) as executor:
        for stage in BATCH_STAGES:
            before = scheduler_counts(stats)
            t0 = time.perf_counter()
            (result,) = run_pipeline(
                WorkDir.at(work), config, capture=capture, only=stage, executor=executor, progress=False
            )
            wall = time.perf_counter() - t0
            after = scheduler_counts(stats)
            split = {k.rsplit("-", 2)[0]: 0 for k in after}
            for k, v in after.items():
                split[k.rsplit("-", 2)[0]] += v[0] - before.get(k, [0, 0])[0]
            by_prefix = {k: n for k, n in split.items() if n}
            tasks = sum(by_prefix.values())
            busy = sum(v[1] - before.get(k, [0, 0])[1] for k, v in after.items())
            if result.status == "failed":
                raise SystemExit(f"{stage} failed: {result.reason}")
            rows.append(
                {
                    "stage": stage,
                    "status": result.status,
                    "wall_s": wall,
                    "work_s": busy,
                    "tasks": tasks,
                    "tasks_by_function": by_prefix,
                }
            )
            print(
                f"  {stage}: {wall:.1f} s wall, {busy:.1f} s work, {tasks} tasks", file=sys.stderr, flush=True
            )
    return rows


def record_sizes(work: Path, top: int = 12) -> list[tuple[str, int]]:
    """The largest JSON records and manifests of WORK (relative path, bytes)."""
    files = [(str(p.relative_to(work)), p.stat().st_size) for p in work.rglob("*.json")]
    return sorted(files, key=lambda f: -f[1])[:top]


def main() -> None:
    from test_cluster_resume import DaskProcesses
    from tree_hash import tree_hash

    from lightstage.simulator.simulate import simulate_capture

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", type=Path)
    ap.add_argument("--groups", default=None, help="group selector (default: all 9)")
    ap.add_argument("--lights", default=None, help="light selector (default: all 331)")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument(
        "--kill-after", type=int, default=0, help="kill the scheduler at N processed frames, resume"
    )
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument(
        "--config",
        default="default",
        help="pipeline config (calibrate: {num_threads: 1} makes SfM, and so the whole tree, run-to-run identical)",
    )
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    capture = args.out / "capture"
    t0 = time.perf_counter()
    if not (capture / "stage.yaml").is_file():
        simulate_capture(capture, "paper-512", 0, args.groups, None, args.lights, args.workers, False, False)
    simulate_s = time.perf_counter() - t0
    print(f"capture ready in {simulate_s:.0f} s", file=sys.stderr)
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONUNBUFFERED": "1"}
    logs = args.out / "logs"
    logs.mkdir(exist_ok=True)
    work = args.out / "work"
    shutil.rmtree(work, ignore_errors=True)
    shutil.rmtree(args.out / "work-killed", ignore_errors=True)
    cluster = DaskProcesses(logs, env, args.workers)
    try:
        address = cluster.start()
        rows = run_stages(capture, work, address, args.workers, args.config)
        peaks = {
            "scheduler": vm_hwm_mb(cluster.scheduler.pid),
            "workers": [vm_hwm_mb(p.pid) for p in cluster.procs[1:]],
            "client": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
        }
    finally:
        cluster.stop()
    frames = frames_of(work)
    for (
        r
    ) in rows:  # stages without tasks (calibrate, split, bounds) run in this process: no overhead to speak of
        over = (r["wall_s"] * args.workers - r["work_s"]) / max(1, frames) if r["tasks"] else None
        r["overhead_ms_per_frame"] = None if over is None else 1e3 * over
    result = {
        "machine": platform.processor() or platform.machine(),
        "cpus": os.cpu_count(),
        "frames": frames,
        "simulate_s": simulate_s,
        "workers": args.workers,
        "groups": args.groups,
        "lights": args.lights,
        "stages": rows,
        "peak_rss_mb": peaks,
        "records": record_sizes(work),
    }
    if args.kill_after:
        result["resume"] = kill_and_resume(capture, args, env, logs, tree_hash(work))
    text = json.dumps(result, indent=1)
    print(text)
    if args.json:
        args.json.write_text(text)


def kill_and_resume(capture: Path, args, env: dict[str, str], logs: Path, reference: str) -> dict:
    """Kill the scheduler mid-preprocess, restart everything, rerun `run --to shard`; equal to `reference`?"""
    import signal
    import subprocess
    import threading

    from test_cluster_resume import DaskProcesses
    from tree_hash import tree_hash

    work = args.out / "work-killed"
    cmd = [sys.executable, "-m", "lightstage.pipelines.cli", "run", str(capture), "--work", str(work)]
    cmd += ["--to", "shard", "--quiet"] + (["--config", args.config] if args.config != "default" else [])
    cluster = DaskProcesses(logs, env, args.workers)
    try:
        address = cluster.start()
        proc = subprocess.Popen([*cmd, "--scheduler", address], env=env, stderr=subprocess.PIPE, text=True)

        def killer() -> None:
            while proc.poll() is None and frames_of(work) < args.kill_after:
                time.sleep(0.2)
            if proc.poll() is None:
                os.kill(cluster.scheduler.pid, signal.SIGKILL)

        threading.Thread(target=killer, daemon=True).start()
        first = proc.wait()
        killed_at = frames_of(work)
        cluster.stop()
        address = cluster.start()
        second = subprocess.run([*cmd, "--scheduler", address], env=env, capture_output=True, text=True)
    finally:
        cluster.stop()
    mine, theirs = [], []
    tree_hash(work, listing=mine)
    tree_hash(args.out / "work", listing=theirs)
    differ = sorted({line.split("  ", 1)[1] for line in set(mine) ^ set(theirs)})
    return {
        "killed_at_frames": killed_at,
        "first_exit": first,
        "rerun_exit": second.returncode,
        "identical_to_uninterrupted": second.returncode == 0 and tree_hash(work) == reference,
        "differing_files": differ,
    }


if __name__ == "__main__":
    main()
