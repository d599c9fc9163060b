"""`lightstage demo`: simulate a capture, run the whole pipeline on it with the `cpu` training config, relight
the model with an environment map and write WORK/report.md with PNGs a person can look at.

Every step is resumable: a rerun reuses the simulated capture and skips up-to-date stages.
"""

from __future__ import annotations

import dataclasses
import json
import os
import shutil
import sys
import time
from pathlib import Path
from typing import Any

from lightstage.atomic import write_json_atomic
from lightstage.pipelines.demo_report import write_report
from lightstage.workdir import WorkDir

ENVMAP_DIR = Path(__file__).resolve().parents[2] / "shared" / "data" / "envmaps"
RELIGHT_LIGHTS = "16"


def _say(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def simulate(work: WorkDir, settings: Any, progress: bool = True) -> Path:
    """Simulate the demo capture (config `demo:` section) into WORK/capture; skipped when a finished one with
    the same settings is there."""
    from lightstage.simulator.simulate import simulate_capture

    capture = work.root / "capture"
    marker = work.root / ".demo-capture.json"
    wanted = dataclasses.asdict(settings)
    preset, seed = settings.preset, settings.seed
    if marker.is_file() and json.loads(marker.read_text()) == wanted and (capture / "capture.yaml").is_file():
        _say(f"demo: reusing the simulated {preset!r} capture in {capture}")
        return capture
    if capture.exists():
        shutil.rmtree(capture)
    _say(f"demo: simulating the {preset!r} capture (seed {seed}) into {capture}")
    t0 = time.perf_counter()
    simulate_capture(
        capture,
        preset=preset,
        seed=seed,
        groups=settings.groups or None,
        cameras=settings.cameras or None,
        lights=settings.lights or None,
        progress=progress,
    )
    _say(f"demo: simulated in {time.perf_counter() - t0:.0f} s")
    write_json_atomic(marker, wanted)
    return capture


def demo_config(
    config_path: str | os.PathLike[str] | None, workers: int | None, scheduler: str | None
) -> Any:
    """The demo's pipeline config: the built-in `demo` (`cpu` training config) unless a file is given."""
    from lightstage.pipelines.config import load_pipeline_config

    config = load_pipeline_config(config_path if config_path is not None else "demo")
    return config.with_cluster(workers=workers, scheduler=scheduler)


def run_demo(
    work_dir: str | os.PathLike[str],
    *,
    config_path: str | os.PathLike[str] | None = None,
    preset: str | None = None,
    seed: int | None = None,
    workers: int | None = None,
    scheduler: str | None = None,
    progress: bool = True,
) -> Path:
    """Simulate, run every stage, relight and write the report; returns the report's path."""
    from lightstage.pipelines.runner import run_pipeline

    t0 = time.perf_counter()
    work = WorkDir.at(Path(work_dir).resolve())
    work.root.mkdir(parents=True, exist_ok=True)
    config = demo_config(config_path, workers, scheduler)
    settings = config.demo
    if preset is not None or seed is not None:
        settings = dataclasses.replace(
            settings,
            preset=preset or settings.preset,
            seed=settings.seed if seed is None else seed,
            **({"lights": "", "cameras": "", "groups": ""} if preset else {}),
        )
    capture = simulate(work, settings, progress)
    results = run_pipeline(work, config, capture=capture, progress=progress)
    timings = {r.stage: round(r.seconds, 1) for r in results}
    relit = relight(work, progress)
    viewer = build_demo_viewer(work, progress)
    report = write_report(work, timings, relit, time.perf_counter() - t0, _describe(settings), viewer)
    _say(f"demo: finished in {time.perf_counter() - t0:.0f} s")
    print(f"demo report: {report}")
    print(f"  pictures:  {work.root / 'report'}")
    print(f"  stage reports: {work.root / 'reports'}; evaluation images: {work.eval_dir}")
    return report


def _describe(settings: Any) -> str:
    subsets = [f"{k} {getattr(settings, k)}" for k in ("groups", "cameras", "lights") if getattr(settings, k)]
    return f"{settings.preset} (seed {settings.seed}" + (f"; {', '.join(subsets)}" if subsets else "") + ")"


# ---- relighting ------------------------------------------------------------------------------------------
def sky_envmap(path: Path, width: int = 64, height: int = 32) -> Path:
    """A synthetic lat-long sky (lightstage.training.envmap.procedural_sky) written as EXR."""
    from lightstage.frames import write_exr
    from lightstage.training.envmap import procedural_sky

    write_exr(path, procedural_sky(width, height))
    return path


def pick_envmap(work: WorkDir) -> Path:
    """A real envmap from the shared data folder when present, else a synthetic sky written into the report."""
    env_dir = Path(os.environ.get("LIGHTSTAGE_ENVMAPS", ENVMAP_DIR))
    found = sorted(env_dir.glob("*.exr")) if env_dir.is_dir() else []
    if found:
        return found[0]
    return sky_envmap(work.root / "report" / "sky.exr")


def relight(work: WorkDir, progress: bool) -> dict[str, Any]:
    """Relight the trained model with an envmap (median cut, a few dozen lights) for the first calibrated view."""
    from lightstage.training.relight import RelightConfig, run_relight

    envmap = pick_envmap(work)
    out = work.root / "relight"
    done = out / "relight.json"
    if done.is_file():
        summary = json.loads(done.read_text())
        if summary.get("envmap") == str(envmap):
            return summary
    _say(f"demo: relighting with {envmap.name} ({RELIGHT_LIGHTS} median-cut lights)")
    config = RelightConfig(envmap=str(envmap), lights=RELIGHT_LIGHTS, out=str(out))
    return run_relight(work, config, progress=progress)


# The demo's viewer: 3 calibrated views of the ring with a novel view after each, 24 stage lights for the model
# (25-60 CPU-s on the demo model with the machine idle or busy; `lightstage view WORK` builds the full default).
DEMO_VIEWER = {"views": 3, "novel": 1, "basis_lights": 24}


def build_demo_viewer(work: WorkDir, progress: bool) -> dict[str, Any]:
    """WORK/viewer: the relighting viewer of the demo's capture and model (reused when up to date)."""
    from lightstage.viewer.build import ViewerConfig, build_key, build_viewer, is_current

    config = ViewerConfig(**DEMO_VIEWER)
    bundle = work.root / "viewer"
    if is_current(bundle, build_key(work, config)):
        return json.loads((bundle / "manifest.json").read_text())
    _say("demo: building the relighting viewer (WORK/viewer)")
    return build_viewer(work, config, bundle, progress=progress)
