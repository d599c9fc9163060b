"""Simulated light-stage captures with ground truth: `simulate_capture(out, preset, seed)` writes a complete raw
capture (stage.yaml with NOMINAL geometry, capture.yaml, half EXR frames) plus `out/ground_truth/` (true
geometry, masks, clean renders, scene description) and `out/contact_sheet.png`.

Presets: `tiny` (unit tests, seconds), `small` (the demo; large enough for SfM), `paper` (the full reference
stage; only with --groups/--cameras/--lights subsets, for benchmarks). Deterministic for a seed.
"""

from __future__ import annotations

import json
import os
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from lightstage.atomic import write_json_atomic
from lightstage.cameras import PinholeCamera
from lightstage.capture.layout import (
    CAPTURE_FILE,
    DEFAULT_PATH_TEMPLATE,
    STAGE_FILE,
    CaptureInfo,
    save_capture_info,
)
from lightstage.capture.presets import PAPER_RESOLUTION, make_stage
from lightstage.capture.probe import ProbeInfo, save_probe_info
from lightstage.capture.stage import Stage
from lightstage.errors import LightstageError
from lightstage.executor import Executor, local_executor
from lightstage.ids import ViewId
from lightstage.records.calibration import Calibration, ViewCalibration
from lightstage.records.ground_truth import CLEAN_TEMPLATE, FOLDER, GroundTruth
from lightstage.simulator.cases import apply_scene_cases, apply_stage_cases, check_cases
from lightstage.simulator.geometry import TrueGeometry, true_geometry
from lightstage.simulator.probe import (
    ProbeJob,
    ProbeSettings,
    ProbeViewRecord,
    probe_ground_truth,
    probe_jobs,
    render_probe_view,
)
from lightstage.simulator.render import ViewJob, ViewRecord, render_view
from lightstage.simulator.scene import SimScene, default_scene, led_intensities
from lightstage.simulator.shading import cast_view, render_hits

CONTACT_SHEET = "contact_sheet.png"


@dataclass(frozen=True)
class SimPreset:
    """Counts and raw resolution of a simulated stage, and how many lights get clean GT renders."""

    name: str
    num_groups: int
    num_cameras: int
    num_lights: int
    width: int
    height: int
    clean_lights: int = 4  # lights (spread over the sphere) rendered clean for every view
    requires_selection: bool = False  # `paper`: too big to simulate whole
    camera_distance: float | None = None  # metres from the centre; None: on the light sphere (1.5 m)
    realism: str = "clean"  # "stage": a real stage's lit backdrop, sensor, LEDs (scene.default_scene)

    @property
    def num_frames(self) -> int:
        return self.num_groups * self.num_cameras * self.num_lights


SIM_PRESETS: dict[str, SimPreset] = {
    "tiny": SimPreset("tiny", 9, 4, 12, 256, 172, clean_lights=3, camera_distance=1.1),
    "small": SimPreset("small", 9, 20, 32, 768, 512, clean_lights=4, camera_distance=1.1, realism="stage"),
    "paper": SimPreset("paper", 9, 20, 331, *PAPER_RESOLUTION, clean_lights=2, requires_selection=True),
    # the paper's geometry and frame count (9 x 20 x 331 = 59,580 frames) at a raw size that simulates whole:
    # the scale bench's capture, and tests' paper-geometry captures (with a subset of lights)
    "paper-512": SimPreset("paper-512", 9, 20, 331, 512, 344, clean_lights=2),
}


# ---- selection -----------------------------------------------------------------------------------------
def _parse_indices(
    spec: str | list | tuple | None, count: int, what: str, names: list[str] | None = None
) -> list[int]:
    """Parse a selector ("0,3,5-8", "0-31:2" (with a step), names, or a list) into sorted unique indices."""
    if spec is None:
        return list(range(count))
    items = spec.split(",") if isinstance(spec, str) else list(spec)
    out: set[int] = set()
    for raw in items:
        item = str(raw).strip()
        if not item:
            continue
        if names is not None and item in names:
            out.add(names.index(item))
            continue
        try:
            if "-" in item[1:]:
                a, b = item.split("-", 1)
                b, _, step = b.partition(":")
                lo, hi, st = int(a), int(b), int(step or 1)
                if lo > hi or st < 1:
                    raise ValueError
                out.update(range(lo, hi + 1, st))
            else:
                out.add(int(item))
        except ValueError:
            known = f" or one of {', '.join(names[:6])}{'...' if len(names) > 6 else ''}" if names else ""
            raise LightstageError(
                f"--{what}: cannot parse {item!r} (use indices like 0,3,5-8 or 0-31:2{known})"
            ) from None
    bad = [i for i in out if not 0 <= i < count]
    if bad:
        raise LightstageError(f"--{what}: index {bad[0]} out of range (the preset has {count} {what})")
    if not out:
        raise LightstageError(f"--{what}: empty selection")
    return sorted(out)


def _select_stage(full: Stage, groups: list[int], cameras: list[int], lights: list[int]) -> Stage:
    """A stage restricted to the selected groups/cameras/lights (lights renumbered 0..k-1, as stage.yaml needs)."""
    sel_lights = tuple(replace(full.lights[i], index=k) for k, i in enumerate(lights))
    return replace(
        full,
        cameras=tuple(full.cameras[i] for i in cameras),
        lights=sel_lights,
        groups=tuple(full.groups[i] for i in groups),
    )


def clean_light_choice(num_lights: int, count: int) -> list[int]:
    """Lights with clean GT renders: spread evenly over the index range (so over the light sphere)."""
    count = min(count, num_lights)
    return sorted({int(round(x)) for x in np.linspace(num_lights * 0.15, num_lights - 1, count)})


# Every light of the last CLEAN_TEST_CAMERAS cameras is rendered clean too: they hold the test views of the
# `paper` protocol (the paper's cameras 19-20; the last max(1, round(10%)) of the cameras, see dataset.split), so
# evaluation can score a perfect prediction against the same test frames (the ceiling).
CLEAN_TEST_CAMERAS = 2


def clean_camera_choice(camera_ids: tuple[str, ...] | list[str]) -> list[str]:
    """Cameras with a clean GT render of every light: the last CLEAN_TEST_CAMERAS of the capture's cameras."""
    return list(camera_ids)[-CLEAN_TEST_CAMERAS:]


# ---- the entry point ---------------------------------------------------------------------------------------
def simulate_capture(
    out: Path,
    preset: str = "tiny",
    seed: int = 0,
    groups: Any = None,
    cameras: Any = None,
    lights: Any = None,
    workers: int | None = None,
    progress: bool = True,
    probe: bool = True,
    realism: str | None = None,
    cases: Any = None,
) -> Path:
    """Simulate a raw capture with ground truth into `out` (created; must be empty or absent); returns `out`.

    `probe`: also write the mirror-ball light-probe frames (probe/, see capture.probe) and
    ground_truth/probe.json (its views queued after the capture views, in the same pool). `realism`: "stage"
    or "clean" (default: the preset's; see scene.default_scene). `cases`: names of real captures' failure cases
    (simulator/cases.py: grey-object, candle, camera-side-lights, srgb8, ...), combined."""
    if preset not in SIM_PRESETS:
        raise LightstageError(f"unknown simulator preset {preset!r} (known: {', '.join(SIM_PRESETS)})")
    if not isinstance(seed, int) or seed < 0:
        raise LightstageError(f"seed must be a non-negative integer, got {seed!r}")
    p = SIM_PRESETS[preset]
    cases = check_cases(cases)
    out = Path(out)
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise LightstageError(f"{out}: output exists and is not an empty directory")
    if p.requires_selection and (groups is None or cameras is None or lights is None):
        raise LightstageError(
            f"preset {preset!r} has {p.num_frames} frames of {p.width}x{p.height}; "
            "select a subset with --groups, --cameras and --lights"
        )
    full = make_stage(
        f"sim-{preset}",
        p.num_cameras,
        p.num_lights,
        p.width,
        p.height,
        num_groups=p.num_groups,
        camera_distance=p.camera_distance,
    )
    full = apply_stage_cases(full, cases)
    gsel = _parse_indices(groups, len(full.groups), "groups", full.group_names)
    csel = _parse_indices(cameras, len(full.cameras), "cameras", full.camera_ids)
    lsel = _parse_indices(lights, len(full.lights), "lights")
    truth_full = true_geometry(full, seed)
    realism = realism or p.realism
    scene = apply_scene_cases(default_scene(texture_seed=seed, realism=realism), cases)
    if scene.led_spread or scene.led_colour_spread:  # measured LED intensities go into stage.yaml
        leds = led_intensities(len(full.lights), seed, scene.led_spread, scene.led_colour_spread)
        full = replace(full, lights=tuple(replace(lt, intensity=tuple(leds[lt.index])) for lt in full.lights))
    stage = _select_stage(full, gsel, csel, lsel)
    truth = replace(truth_full, lights_rig=truth_full.lights_rig[lsel])

    start = time.perf_counter()
    out.mkdir(parents=True, exist_ok=True)
    stage.save(out / STAGE_FILE)
    notes = {
        "simulator": "lightstage.simulator.simulate",
        "preset": preset,
        "seed": seed,
        "realism": realism,
        "cases": list(cases),
        "ground_truth": FOLDER,
        "source_light_indices": lsel if len(lsel) != len(full.lights) else "all",
    }
    save_capture_info(
        CaptureInfo(DEFAULT_PATH_TEMPLATE, 1.0, "sim-translucent-wax", notes), out / CAPTURE_FILE
    )
    clean = clean_light_choice(len(stage.lights), p.clean_lights)
    clean_cams = clean_camera_choice(stage.camera_ids)
    _write_ground_truth(GroundTruth.of(out), stage, truth, scene, clean, seed, preset, clean_cams)

    jobs = [
        ViewJob(
            root=out,
            group=full.groups[gi].name,
            camera=full.cameras[ci].id,
            group_index=gi,
            camera_index=ci,
            camera_model=truth.view_camera(stage, full.groups[gi].name, full.cameras[ci].id),
            light_positions=truth.light_positions(full.groups[gi].name),
            light_ids=tuple(range(len(lsel))),
            light_seed_ids=tuple(lsel),
            clean_lights=tuple(range(len(lsel))) if full.cameras[ci].id in clean_cams else tuple(clean),
            scene=scene,
            saturation=stage.saturation,
            seed=seed,
            path_template=DEFAULT_PATH_TEMPLATE,
            attributes={"lightstage_simulator": f"{preset} seed {seed}"},
            light_intensities=stage.light_intensities(),
        )
        for gi in gsel
        for ci in csel
    ]
    settings = ProbeSettings()
    probe_info, pjobs = (
        _probe_jobs(out, stage, truth, scene, seed, preset, full, lsel, settings) if probe else (None, [])
    )
    # one map: the capture views, then the probe's (cheaper) views, so no worker idles at a barrier between
    # the two kinds and the pool is spawned once
    with local_executor(_pool_size(workers, len(jobs) + len(pjobs))) as executor:
        results = _run_jobs(jobs + pjobs, executor, progress, render_job)
    records = results[: len(jobs)]
    if probe_info is not None:
        save_probe_info(probe_info, out)
        probe_truth = probe_ground_truth(truth, settings, list(probe_info.positions), results[len(jobs) :])
        write_json_atomic(GroundTruth.of(out).probe, probe_truth)
    nuisances = {
        "bulbs_in_view": [
            {"group": r.group, "camera": r.camera, "light": lt, "pixels": n}
            for r in records
            for lt, n in r.bulbs.items()
        ],
        "flares": [
            {"group": r.group, "camera": r.camera, "light": lt, "strength": s}
            for r in records
            for lt, s in r.flares.items()
        ],
    }
    write_json_atomic(GroundTruth.of(out).nuisances, nuisances)
    write_contact_sheet(out, stage, clean)
    if progress:
        n = len(jobs) * len(lsel)
        if probe_info is not None:
            print(
                f"simulated {len(pjobs) * (len(lsel) + 1)} probe frames ({len(probe_info.positions)} positions x "
                f"{len(stage.cameras)} cameras, {len(lsel)} lights + ambient)"
            )
        print(f"simulated {n} frames ({len(jobs)} views) into {out} in {time.perf_counter() - start:.1f} s")
    return out


def _probe_jobs(
    out: Path,
    stage: Stage,
    truth: TrueGeometry,
    scene: SimScene,
    seed: int,
    preset: str,
    full: Stage,
    lsel: list[int],
    settings: ProbeSettings,
) -> tuple[ProbeInfo, list[ProbeJob]]:
    """The mirror-ball probe's probe.yaml info and view jobs (seed streams indexed in the full preset)."""
    return probe_jobs(
        out,
        stage,
        truth,
        scene,
        seed,
        {g.name: i for i, g in enumerate(full.groups)},
        {c.id: i for i, c in enumerate(full.cameras)},
        tuple(lsel),
        settings,
        attributes={"lightstage_simulator": f"{preset} seed {seed} probe"},
    )


def render_job(job: ViewJob | ProbeJob) -> ViewRecord | ProbeViewRecord:
    """Render one capture view (render.render_view) or probe view (probe.render_probe_view)."""
    return render_probe_view(job) if isinstance(job, ProbeJob) else render_view(job)


def _pool_size(workers: int | None, num_jobs: int) -> int:
    """Worker processes for `num_jobs` views: `workers` (default: available cores, at most 8); 1 inside a
    daemon process (e.g. a dask worker), which may not have children."""
    import multiprocessing as mp

    n = workers if workers is not None else min(len(os.sched_getaffinity(0)), 8)
    n = max(1, min(n, num_jobs))
    if mp.current_process().daemon:
        n = 1
    return n


def _run_jobs(
    jobs: list[Any],
    executor: Executor,
    progress: bool,
    render: Any = render_view,
    desc: str = "simulate views",
) -> list[Any]:
    """Render views through the executor (its pool workers have one library thread each); job order."""
    return executor.map(render, jobs, desc=desc, unit="view", progress=progress)


def _write_ground_truth(
    gt: GroundTruth,
    stage: Stage,
    truth: TrueGeometry,
    scene: SimScene,
    clean: list[int],
    seed: int,
    preset: str,
    clean_cameras: list[str] | tuple[str, ...] = (),
) -> None:
    """geometry.json (true cameras, lights, axis, yaws), scene.json, clean.json."""
    views = {}
    for g in stage.groups:
        for c in stage.cameras:
            cam = truth.view_camera(stage, g.name, c.id)
            views[ViewId(g.name, c.id)] = ViewCalibration(cam.K, cam.R, cam.t, stage.width, stage.height)
    Calibration(
        method="ground_truth",
        views=views,
        light_positions={g.name: truth.light_positions(g.name) for g in stage.groups},
        axis=truth.axis,
        yaws_deg={g.name: truth.yaws_deg[g.name] for g in stage.groups},
    ).save(gt.geometry)
    sc = scene.to_dict()
    sc["seed"] = seed
    sc["preset"] = preset
    sc["units"] = "m; radiance in the stage's linear units (capture exposure_scale 1)"
    write_json_atomic(gt.scene, sc)
    write_json_atomic(
        gt.clean_info,
        {
            "lights": clean,
            "views": "all",
            # and every light of these cameras in every group (the test views: evaluation's ceiling)
            "every_light_cameras": list(clean_cameras),
            "path_template": CLEAN_TEMPLATE,
            "content": "noise-free, unclipped float32 radiance of object + stand; background, bulbs, flare = 0",
        },
    )


def write_contact_sheet(root: Path, stage: Stage, lights: list[int], max_views: int = 4) -> Path:
    """A grid of a few views x lights of the raw frames, tonemapped (one exposure), as contact_sheet.png."""
    import cv2

    from lightstage.frames import read_exr, write_image
    from lightstage.tonemap import tonemap_u8

    cams = stage.camera_ids
    views = [(stage.groups[(k * 2) % len(stage.groups)].name, cams[k % len(cams)]) for k in range(max_views)]
    views = list(dict.fromkeys(views))
    lights = lights[:4] if lights else [0]
    tile_w = min(stage.width, 320)
    tile_h = int(round(stage.height * tile_w / stage.width))
    tiles = []
    for g, c in views:
        row = []
        for lt in lights:
            img = read_exr(root / DEFAULT_PATH_TEMPLATE.format(group=g, camera=c, light=lt)).astype(
                np.float32
            )
            row.append(cv2.resize(img, (tile_w, tile_h), interpolation=cv2.INTER_AREA))
        tiles.append(row)
    pad = 4
    sheet = np.zeros((len(views) * (tile_h + pad) + pad, len(lights) * (tile_w + pad) + pad, 3), np.float32)
    for i, row in enumerate(tiles):
        for j, img in enumerate(row):
            y, x = pad + i * (tile_h + pad), pad + j * (tile_w + pad)
            sheet[y : y + tile_h, x : x + tile_w] = img
    sheet_u8 = tonemap_u8(sheet, exposure=1.6)
    path = root / CONTACT_SHEET
    write_image(path, sheet_u8)
    return path


# ---- ground-truth access for tests and scorers -------------------------------------------------------------
def load_scene(capture_root: Path) -> SimScene:
    """The SimScene of a simulated capture (from ground_truth/scene.json)."""
    path = GroundTruth.of(capture_root).scene
    try:
        return SimScene.from_dict(json.loads(path.read_text()))
    except OSError as e:
        raise LightstageError(f"{path}: cannot read ({e.strerror}); is this a simulated capture?") from None
    except json.JSONDecodeError as e:
        raise LightstageError(f"{path}: invalid JSON ({e})") from None


def load_truth(capture_root: Path) -> Calibration:
    """The true geometry of a simulated capture (ground_truth/geometry.json)."""
    return Calibration.load(GroundTruth.of(capture_root).geometry)


def render_clean(
    source: Path | SimScene,
    group: str,
    camera: str | PinholeCamera,
    light_positions: np.ndarray,
    intensities: Any = None,
) -> np.ndarray:
    """(H, W, 3) float32 noise-free, unclipped radiance of object + stand for any set of point lights.

    `source`: a simulated capture root (scene and true camera read from ground_truth/) or a SimScene, in which
    case `camera` must be a PinholeCamera. `intensities`: one per light (scalar or RGB); default: the stage's."""
    if isinstance(source, SimScene):
        scene = source
        if not isinstance(camera, PinholeCamera):
            raise LightstageError("render_clean with a SimScene needs a PinholeCamera")
        cam = camera
    else:
        scene = load_scene(source)
        if isinstance(camera, PinholeCamera):
            cam = camera
        else:
            truth = load_truth(source)
            view = truth.views.get(ViewId(group, camera))
            if view is None:
                raise LightstageError(f"{source}: no view {group}/{camera} in the ground truth")
            cam = view.camera(downscale=1)
    light_positions = np.atleast_2d(np.asarray(light_positions, np.float64))
    if intensities is None:
        intensities = np.full(len(light_positions), scene.light_intensity, np.float32)
    hits = cast_view(scene, cam.K, cam.R, cam.t, cam.width, cam.height)
    return render_hits(scene, hits, light_positions, intensities)


__all__ = [
    "SIM_PRESETS",
    "SimPreset",
    "simulate_capture",
    "render_clean",
    "load_scene",
    "load_truth",
    "write_contact_sheet",
]
