"""CPU seconds per simulated frame, by kind: a capture view's frames (raw half PIZ + its clean float32 renders)
and a probe view's frames, for the demo's `small` preset, one process, one library thread.

    python bench/simulate_cost.py [--views 4] [--repeats 2] [--source DIR]

Renders the first `--views` capture views (group 000, cameras 0..; the last two of them render every light
clean, as the test cameras do) and as many probe views with lights 0-31:2, into a temporary folder, and prints
JSON: CPU seconds per view and per frame of each kind (best of `--repeats`; process time, so another load on
the machine inflates it less than wall time, though not to nothing). `--source DIR`: import the simulator from
DIR/simulator instead (e.g. an older tree from `git archive REV simulator | tar -x -C DIR`), to compare
versions in the same run and machine state.
"""

from __future__ import annotations

import argparse
import json
import platform
import tempfile
import time
from pathlib import Path


def _use_source(source: str | None) -> None:
    """Point the lightstage.simulator package at another copy of the folder (before its modules load)."""
    if source:
        import lightstage.simulator as sim

        sim.__path__[:] = [str(Path(source) / "simulator")]


def collect_jobs(root: Path, views: int) -> tuple[list, list]:
    """The capture and probe view jobs simulate_capture would run for group 000, cameras 0..views-1."""
    from lightstage.simulator import simulate as S
    from lightstage.simulator.probe import ProbeJob

    jobs: list = []

    def grab(batch: list, *args: object, **kwargs: object) -> list:
        jobs.extend(batch)
        return []

    real = S._run_jobs
    S._run_jobs = grab
    try:
        S.simulate_capture(
            root, preset="small", seed=0, groups="0", cameras=f"0-{views - 1}", lights="0-31:2",
            workers=1, progress=False, probe=True,
        )  # fmt: skip
    except Exception:  # noqa: BLE001 - with no frames rendered, the contact sheet fails: expected
        pass
    finally:
        S._run_jobs = real
    probe = [j for j in jobs if isinstance(j, ProbeJob)]
    capture = [j for j in jobs if not isinstance(j, ProbeJob)]
    return capture, probe[:views]


def measure(fn: object, jobs: list, repeats: int) -> float:
    """Best CPU seconds of running fn over all jobs."""
    best = float("inf")
    for _ in range(repeats):
        t = time.process_time()
        for j in jobs:
            fn(j)
        best = min(best, time.process_time() - t)
    return best


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--views", type=int, default=4)
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--source", default=None)
    args = ap.parse_args()
    _use_source(args.source)
    from lightstage.simulator.probe import render_probe_view
    from lightstage.simulator.render import render_view
    from lightstage.threads import set_library_threads

    set_library_threads(1)
    with tempfile.TemporaryDirectory() as tmp:
        capture, probe = collect_jobs(Path(tmp) / "cap", args.views)
        render_view(capture[0])  # imports, caches
        cap_s = measure(render_view, capture, args.repeats)
        probe_s = measure(render_probe_view, probe, args.repeats)
    raw = sum(len(j.light_ids) for j in capture)
    clean = sum(len(j.clean_lights) for j in capture)
    probe_frames = sum(len(j.light_ids) + 1 for j in probe)
    print(
        json.dumps(
            {
                "source": args.source or "working tree",
                "machine": platform.processor() or platform.machine(),
                "capture_views": len(capture),
                "raw_frames": raw,
                "clean_frames": clean,
                "capture_cpu_s_per_view": round(cap_s / len(capture), 3),
                "capture_cpu_s_per_raw_frame_incl_clean": round(cap_s / raw, 4),
                "probe_views": len(probe),
                "probe_frames": probe_frames,
                "probe_cpu_s_per_view": round(probe_s / max(len(probe), 1), 3),
                "probe_cpu_s_per_frame": round(probe_s / max(probe_frames, 1), 4),
            },
            indent=1,
        )
    )


if __name__ == "__main__":
    main()
