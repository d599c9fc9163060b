"""The calibration stage: `run_calibrate(work, config)` writes WORK/calibration/ and WORK/reports/calibration.json.

Methods (explicit, never a silent fallback):
- `nominal`: cameras, lights, axis and yaws straight from stage.yaml.
- `sfm`: pycolmap (`sfm.py`) on the preprocess stage's per-view SfM images + masks (preprocess/sfm_image.py:
  a trimmed mean of a few frames at up to raw resolution), registered to the world frame with the
  nominal rig (centres and orientations) as gauge (`register.py`); fails with a LightstageError naming the views when views stay
  unregistered or residuals exceed the thresholds.
Outputs: calibration.json (the record every later stage reads), colmap/ (sparse model), transforms.json
(nerfstudio, OpenGL), layout.png; the report holds SfM statistics and, when the capture has ground truth,
errors against it.
"""

from __future__ import annotations

import json
import time
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np

from lightstage.atomic import write_json_atomic
from lightstage.calibration.config import CalibrateConfig
from lightstage.calibration.evaluate import ball_centre_errors, light_floor
from lightstage.calibration.observed_lights import observe_lights
from lightstage.cameras import camera_center, scale_intrinsics
from lightstage.capture.layout import Capture, open_capture
from lightstage.errors import LightstageError
from lightstage.executor import Executor
from lightstage.ids import ViewId
from lightstage.records.calibration import Calibration, ViewCalibration
from lightstage.records.ground_truth import GroundTruth
from lightstage.workdir import DOWNSCALE, WorkDir

STAGE = "calibration"


def load_intrinsics(path: str | Path, camera_ids: list[str]) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Per-camera raw-resolution (K, dist) from a `calibrate-intrinsics` JSON file."""
    path = Path(path)
    try:
        d = json.loads(path.read_text())
        cams = d["cameras"]
        out = {
            c: (np.asarray(v["K"], float).reshape(3, 3), np.asarray(v["dist"], float).reshape(5))
            for c, v in cams.items()
        }
    except OSError as e:
        raise LightstageError(f"{path}: cannot read intrinsics ({e.strerror})") from None
    except (KeyError, TypeError, ValueError) as e:
        raise LightstageError(f"{path}: malformed intrinsics file ({type(e).__name__}: {e})") from None
    unknown = sorted(set(out) - set(camera_ids))
    if unknown:
        raise LightstageError(f"{path}: cameras {unknown} are not in the stage")
    return out


def _preprocess_sfm_images(work: WorkDir, capture: Capture) -> tuple[dict[ViewId, tuple[Path, Path]], dict]:
    """Every view's (SfM image, feature mask) from preprocess and their common factor/size/exposure; a clear
    error naming the views when preprocess has not written them (run or rerun `lightstage preprocess`)."""
    views, missing = {}, []
    for v in capture.views():
        img, mask = work.sfm_image(v), work.sfm_mask(v)
        if img.is_file() and mask.is_file():
            views[v] = (img, mask)
        else:
            missing.append(str(v))
    if missing or not work.sfm_info.is_file():
        what = f"{len(missing)} views ({', '.join(missing[:10])}{' ...' if len(missing) > 10 else ''})"
        raise LightstageError(
            f"{work.preprocess_dir}: no SfM image or mask for {what if missing else 'the capture'} "
            f"(or no {work.sfm_info.name}); run `lightstage preprocess` (again, with this version) first"
        )
    try:
        info = json.loads(work.sfm_info.read_text())
        factor, (w, h) = int(info["factor"]), info["size"]
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise LightstageError(f"{work.sfm_info}: unreadable ({e}); rerun `lightstage preprocess`") from None
    st = capture.stage
    if factor < 1 or (st.width // factor, st.height // factor) != (w, h):
        raise LightstageError(
            f"{work.sfm_info}: SfM images are {w}x{h} at raw / {factor}, which does not fit the stage's "
            f"{st.width}x{st.height}; rerun `lightstage preprocess`"
        )
    return views, info


def _sfm_calibration(
    work: WorkDir, capture: Capture, config: CalibrateConfig, intr: dict, log, progress: bool = False
) -> tuple[Calibration, dict[str, Any], Any]:
    from lightstage.calibration.register import Registration, register_rig
    from lightstage.calibration.sfm import SfmOptions, run_sfm

    stage = capture.stage
    views, info = _preprocess_sfm_images(work, capture)
    f, (w, h) = int(info["factor"]), info["size"]
    log(f"SfM images from preprocess: {w}x{h} (raw / {f}), mean of {info['lights']} frames per view")
    sfm_intr = {c: (scale_intrinsics(K, 1.0 / f), dist, w, h) for c, (K, dist) in intr.items()}
    options = SfmOptions(
        max_features=config.max_features,
        mask_erode_px=int(round(config.mask_erode_px * DOWNSCALE / f)),
        first_octave=config.sift_first_octave,
        # The nominal poses are off by the same angle at any resolution: the first round's threshold scales
        # with the image (10 px at the processed resolution, 40 px at raw for a 4x downscale).
        initial_max_reproj_px=10.0 * DOWNSCALE / f,
        refine_rounds=3 if f == DOWNSCALE else 4,
        max_pair_angle_deg=config.max_pair_angle_deg,
        min_pair_neighbours=config.min_pair_neighbours,
        peak_threshold=config.peak_threshold,
        ransac_max_error_px=config.ransac_max_error_px,
        num_threads=config.num_threads,
        seed=config.seed,
        verbose=config.show_colmap_log,
    )
    sfm_dir = work.calibration_dir / "sfm"
    initial = {
        v: (stage.view_camera(v.group, v.camera).R, stage.view_camera(v.group, v.camera).t) for v in views
    }
    colmap_log = work.calibration_dir / "colmap.log"
    result = run_sfm(
        views,
        sfm_intr,
        stage.camera_ids,
        sfm_dir,
        options,
        log=log,
        initial_poses=initial,
        log_path=colmap_log,
    )
    stats = dict(result.stats)
    stats["colmap_log"] = str(colmap_log)
    stats["images"] = {"source": str(work.sfm_info), **info}
    n_needed = int(np.ceil(config.min_registered_fraction * len(views)))
    if len(result.registered) < n_needed:
        raise LightstageError(
            f"SfM registered {len(result.registered)}/{len(views)} views (needs {n_needed}); "
            f"unregistered: {', '.join(map(str, result.unregistered))}"
        )
    mean_err = stats["reprojection_error_px"]["mean"]
    if mean_err is None or mean_err > config.max_mean_reprojection_px:
        raise LightstageError(
            f"SfM mean reprojection error {mean_err} px exceeds {config.max_mean_reprojection_px} px "
            f"(views: {', '.join(map(str, result.registered))})"
        )
    nominal_centres = {c.id: camera_center(c.R, c.t) for c in stage.cameras}

    def register(extra_points: tuple | None = None, scale_prior: tuple | None = None) -> Registration:
        """The gauge fit and turntable registration, optionally with extra nominal points and a measured scale."""
        return register_rig(
            result.sensor_from_rig,
            result.rig_from_world,
            nominal_centres,
            stage.group_names,
            reference_yaw_deg=stage.groups[0].yaw_deg,
            nominal_direction=np.asarray(stage.axis.direction),
            nominal_rotations={c.id: c.R for c in stage.cameras},
            position_sigma_m=config.gauge_position_sigma_mm / 1000.0,
            rotation_sigma_deg=config.gauge_rotation_sigma_deg,
            extra_points=extra_points,
            scale_prior=scale_prior,
        )

    reg = register()
    if reg.rig_fit_rms_m * 1000.0 > config.max_rig_fit_rms_mm:
        raise LightstageError(
            f"SfM rig does not match the nominal rig of stage.yaml: RMS camera-centre misfit "
            f"{reg.rig_fit_rms_m * 1000:.1f} mm > {config.max_rig_fit_rms_mm} mm"
        )
    p_rig = stage.light_positions_rig()
    lights_report, probe_report = observe_lights(work, capture, config, intr, register, reg, log)
    reg, p_rig, gauge_lights = lights_report.pop("_result")
    stats["lights"] = lights_report
    if probe_report is not None:
        stats["probe"] = probe_report
    calib_views = {}
    for v in result.registered:
        R, t = reg.camera_pose(v.group, v.camera)
        K, dist = intr[v.camera]
        calib_views[v] = ViewCalibration(
            np.asarray(K, float), R, t, stage.width, stage.height, np.asarray(dist, float)
        )
    calib = Calibration(
        method="sfm",
        views=calib_views,
        light_positions={g: reg.light_positions(g, p_rig) for g in reg.rig_to_world},
        axis=reg.turntable.axis,
        yaws_deg={g: reg.turntable.yaws_deg[g] for g in stage.group_names if g in reg.turntable.yaws_deg},
    )
    stats["registration"] = {
        "metres_per_sfm_unit": reg.rig_similarity.scale,
        "rig_fit_rms_mm": 1000.0 * reg.rig_fit_rms_m,
        "turntable_rotation_misfit_deg": reg.turntable.rotation_misfit_deg,
        "turntable_translation_misfit_mm": {
            g: 1000.0 * x for g, x in reg.turntable.translation_misfit_m.items()
        },
        "gauge": "world = stage rig frame of group "
        f"{stage.group_names[0]} (similarity fitting the recovered rig camera centres and orientations to the "
        f"nominal ones, sigma {config.gauge_position_sigma_mm} mm / {config.gauge_rotation_sigma_deg} deg"
        + (
            f", and {len(gauge_lights)} observed lights to theirs, sigma {config.light_prior_sigma_mm} mm"
            if gauge_lights
            else ""
        )
        + "), placed at that group's nominal yaw about the fitted axis",
    }
    from lightstage.calibration.export import sfm_tracks

    rec = result.reconstruction
    tracks = sfm_tracks(rec, reg.world_from_sfm, f / DOWNSCALE) if rec is not None else None
    return calib, stats, tracks


def run_calibrate(
    work: WorkDir,
    config: CalibrateConfig | None = None,
    executor: Executor | None = None,
    progress: bool = True,
) -> dict[str, Any]:
    """Calibrate the capture of `work` (see the module doc); returns a small summary. `executor` is unused
    (SfM is one process; pycolmap uses `config.num_threads` threads)."""
    from lightstage.calibration.export import write_colmap_model, write_transforms
    from lightstage.calibration.nominal import nominal_calibration
    from lightstage.calibration.plot import plot_layout

    config = config or CalibrateConfig()
    work = WorkDir.at(work.root) if isinstance(work, WorkDir) else WorkDir.at(work)
    report_path = work.report(STAGE)
    outputs = [
        work.calibration,
        work.calibration_dir / "transforms.json",
        work.calibration_dir / "layout.png",
        work.calibration_dir / "colmap" / "images.bin",
    ]
    if report_path.is_file() and all(p.is_file() for p in outputs):
        try:
            old = json.loads(report_path.read_text())
            if old.get("status") == "ok" and old.get("config_digest") == config.digest():
                Calibration.load(work.calibration)
                return {**old.get("summary", {}), "skipped": True}
        except (OSError, ValueError, LightstageError):
            pass

    def log(msg: str) -> None:
        if progress:
            print(msg, flush=True)

    t0 = time.perf_counter()
    capture = open_capture(work.capture_path())
    stage = capture.stage
    intr = {c.id: (c.K, c.distortion if c.distortion is not None else np.zeros(5)) for c in stage.cameras}
    if config.intrinsics:
        intr.update(load_intrinsics(config.intrinsics, stage.camera_ids))
    report: dict[str, Any] = {
        "stage": STAGE,
        "method": config.method,
        "capture": str(capture.root),
        "config": asdict(config),
        "config_digest": config.digest(),
        "warnings": [],
    }
    try:
        tracks = None
        if config.method == "nominal":
            calib = nominal_calibration(stage, intr if config.intrinsics else None)
            stats: dict[str, Any] = {"num_views": len(calib.views), "num_registered": len(calib.views)}
        else:
            calib, stats, tracks = _sfm_calibration(work, capture, config, intr, log, progress)
        report["warnings"].extend(stats.pop("warnings", []))
        report["sfm" if config.method == "sfm" else "nominal"] = stats
        calib.save(work.calibration)
        report["colmap"] = write_colmap_model(calib, work.calibration_dir / "colmap", tracks, work)
        write_transforms(calib, work.calibration_dir / "transforms.json", work)
        plot_layout(calib, work.calibration_dir / "layout.png")
        gt = GroundTruth.of(capture.root)
        if gt.geometry.is_file():
            from lightstage.calibration.evaluate import compare_to_truth, true_object_points

            truth = Calibration.load(gt.geometry)
            points = true_object_points(gt.scene)
            report["ground_truth"] = compare_to_truth(calib, truth, light_floor(capture, truth), points)
            probe_truth = gt.probe
            if "probe" in stats and probe_truth.is_file():
                report["ground_truth"]["probe_ball_centre_error_mm"] = ball_centre_errors(
                    stats["probe"], probe_truth
                )
    except LightstageError as e:
        report.update(status="failed", error=str(e), seconds=round(time.perf_counter() - t0, 2))
        write_json_atomic(report_path, report)
        raise
    finally:
        if config.method == "sfm" and not config.keep_sfm_workspace:
            import shutil

            shutil.rmtree(work.calibration_dir / "sfm", ignore_errors=True)
    seconds = time.perf_counter() - t0
    summary = {
        "method": config.method,
        "views": len(calib.views),
        "registered": stats.get("num_registered"),
        "seconds": round(seconds, 2),
    }
    if config.method == "sfm":
        summary["mean_reprojection_error_px"] = stats["reprojection_error_px"]["mean"]
    if "ground_truth" in report:
        g = report["ground_truth"]
        summary["rotation_error_deg_max"] = g["raw"]["rotation_error_deg"]["max"]
        summary["camera_centre_error_mm_max"] = g["raw"]["camera_centre_error_mm"]["max"]
    report.update(status="ok", seconds=round(seconds, 2), summary=summary)
    write_json_atomic(report_path, report)
    log(f"calibration ({config.method}): {len(calib.views)} views -> {work.calibration} in {seconds:.1f} s")
    return summary
