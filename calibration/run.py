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

import hashlib
import json
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from lightstage.atomic import write_json_atomic
from lightstage.cameras import camera_center, scale_intrinsics
from lightstage.capture.layout import Capture, open_capture
from lightstage.config import load, require, require_choice
from lightstage.errors import LightstageError
from lightstage.ids import ViewId
from lightstage.records.calibration import Calibration, ViewCalibration
from lightstage.records.ground_truth import GroundTruth
from lightstage.rig import light_position_in_world
from lightstage.workdir import DOWNSCALE, WorkDir

STAGE = "calibration"
METHODS = ("sfm", "nominal")


@dataclass(frozen=True)
class CalibrateConfig:
    """Settings of the calibration stage (defaults suit the simulator's `small` capture)."""

    method: str = "sfm"
    intrinsics: str | None = (
        None  # JSON from `lightstage calibrate-intrinsics` (raw-resolution K + distortion)
    )
    max_mean_reprojection_px: float = 1.0  # SfM fails above this mean reprojection error
    min_registered_fraction: float = 1.0  # SfM fails when fewer views register (1.0: every view)
    max_rig_fit_rms_mm: float = 50.0  # recovered rig vs nominal camera centres; larger = wrong stage.yaml
    max_features: int = 8192
    mask_erode_px: int = 2  # feature-mask erosion in processed pixels (scaled to the SfM images)
    sift_first_octave: int = -1  # -1: SIFT upsamples once (more, finer features; 0 halved the accuracy)
    max_pair_angle_deg: float = 90.0  # match views whose nominal camera centres are within this angle
    # World-frame gauge: the similarity that best fits the nominal rig's camera centres AND orientations, given
    # the stage's mounting tolerances (per axis); 0 deg: centres only (Umeyama). See docs/calibration.md.
    gauge_position_sigma_mm: float = 3.0
    gauge_rotation_sigma_deg: float = 0.2
    # Lights seen directly by cameras (clipped bulbs in the processed frames) are moved onto their rays /
    # triangulated, with the nominal position as prior (per-axis sigma); the others keep nominal positions.
    observe_bulbs: bool = True
    light_prior_sigma_mm: float = 3.0  # also the lights' mounting tolerance when they join the gauge
    lights_in_gauge: bool = True  # observed lights join the camera centres/orientations in the gauge fit
    bulb_pixel_sigma: float = 0.1  # disc-centre + camera-direction uncertainty, processed pixels
    # a light further off its nominal position (in sigmas) leaves the gauge
    light_gauge_max_sigma: float = 4.0
    # A mirror-ball probe capture (capture/probe.py), when the capture has one, locates every light it mirrors.
    use_probe: bool = True
    # highlight and outline-centre uncertainty, raw pixels (5x what the simulator's frames give: real optics)
    probe_pixel_sigma: float = 0.01
    # camera rotation uncertainty after SfM (its shape error; not magnified by the mirror)
    probe_rotation_sigma_deg: float = 0.01
    probe_distance_sigma_mm: float = 0.2  # camera-to-ball distance uncertainty (cameras' relative positions)
    probe_refine_distances: bool = True  # fit each view's camera-to-ball distance together with the lights
    probe_scale: bool = True  # the ball's known radius fixes the rig's metric scale in the gauge
    probe_radius_sigma_mm: float = 0.005  # tolerance of the ball's radius
    peak_threshold: float = 0.004
    ransac_max_error_px: float = 2.0
    num_threads: int = 2
    seed: int = 0
    keep_sfm_workspace: bool = False  # keep WORK/calibration/sfm (images, database) for debugging
    show_colmap_log: bool = False  # echo COLMAP's log (always in WORK/calibration/colmap.log) to stderr

    def __post_init__(self) -> None:
        require_choice(self.method, "method", METHODS)
        for key in (
            "gauge_position_sigma_mm",
            "light_prior_sigma_mm",
            "bulb_pixel_sigma",
            "light_gauge_max_sigma",
            "probe_pixel_sigma",
        ):
            require(getattr(self, key) > 0, key, f"must be > 0, got {getattr(self, key)!r}")
        for key in (
            "probe_rotation_sigma_deg",
            "probe_distance_sigma_mm",
            "probe_radius_sigma_mm",
            "gauge_rotation_sigma_deg",
        ):
            require(getattr(self, key) >= 0, key, f"must be >= 0, got {getattr(self, key)!r}")
        require(
            0.0 < self.min_registered_fraction <= 1.0,
            "min_registered_fraction",
            f"must be in (0, 1], got {self.min_registered_fraction!r}",
        )

    @classmethod
    def from_dict(cls, d: dict[str, Any] | None) -> CalibrateConfig:
        """The strict loader (`lightstage.config`): unknown keys, wrong types and bad values name the key."""
        return load(cls, d)

    def digest(self) -> str:
        """Hash of the settings that change the outputs (display-only ones left out)."""
        d = asdict(self)
        d.pop("show_colmap_log")
        return hashlib.sha256(json.dumps(d, sort_keys=True).encode()).hexdigest()[:16]


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


def _light_floor(capture: Capture, truth: Calibration) -> Calibration:
    """The truth's rig poses carrying the NOMINAL rig-frame lights: the best a rig-locked light model can do."""
    p_rig = capture.stage.light_positions_rig()
    lights = {g: light_position_in_world(p_rig, y, truth.axis) for g, y in truth.yaws_deg.items()}
    return Calibration("floor", {}, lights, truth.axis, truth.yaws_deg)


def gauge_with_lights(
    register: Callable[[tuple | None], Any],
    src: np.ndarray,
    lights: list[int],
    nominal: np.ndarray,
    sqrt_info: np.ndarray,
    max_sigma: float,
) -> tuple[Any, list[int], dict[str, float]]:
    """Refit the gauge with observed lights as extra points (`register(extra_points)` -> Registration); a light
    whose weighted residual |L (S x - nominal)| exceeds `max_sigma` (a wrong disc, or a camera SfM got wrong) is
    dropped and the gauge refitted once. Returns (registration, lights used, {dropped light: residual})."""
    src, nominal, sqrt_info = np.asarray(src), np.asarray(nominal), np.asarray(sqrt_info)
    reg = register((src, nominal, sqrt_info))
    resid = np.linalg.norm(
        np.einsum("nij,nj->ni", sqrt_info, reg.rig_similarity.apply(src) - nominal), axis=1
    )
    bad = resid > max_sigma
    if not bad.any():
        return reg, list(lights), {}
    keep = ~bad
    rejected = {str(lights[i]): round(float(resid[i]), 2) for i in np.flatnonzero(bad)}
    reg = register((src[keep], nominal[keep], sqrt_info[keep]) if keep.any() else None)
    return reg, [lt for lt, k in zip(lights, keep, strict=True) if k], rejected


def _ball_centre_errors(probe_report: dict[str, Any], truth_path: Path) -> dict[str, float]:
    """Per probe position, the distance (mm) of the fitted ball centre from the true one (rig frame)."""
    try:
        truth = json.loads(truth_path.read_text())["positions"]
        return {
            pos: round(1000.0 * float(np.linalg.norm(np.subtract(c, truth[pos]["ball_centre_rig"]))), 3)
            for pos, c in probe_report["ball_centres_rig_m"].items()
        }
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise LightstageError(f"{truth_path}: unreadable ({e})") from None


def _rig_poses(reg) -> dict[str, tuple[np.ndarray, np.ndarray]]:  # noqa: ANN001 - register.Registration
    """Camera id -> (R, t) camera-from-rig of a registration (what the bulb functions take)."""
    return {c: (T.R, T.t) for c, T in reg.cam_from_rig.items()}


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


def _observe_lights(
    work: WorkDir,
    capture: Capture,
    config: CalibrateConfig,
    intr: dict,
    register: Callable[[tuple | None, tuple | None], Any],
    reg: Any,
    log: Callable[[str], None],
) -> tuple[dict[str, Any], dict[str, Any] | None]:
    """Rig-frame light positions from what observed the lights: bulbs seen directly (`bulbs.py`) and the
    mirror-ball probe (`probe.py`); with `lights_in_gauge` the observed lights first join the gauge fit.
    Returns (report with "_result": (registration, rig-frame lights, lights in the gauge), probe report)."""
    from lightstage.calibration.bulbs import bulb_rays, find_bulbs, processed_intrinsics
    from lightstage.calibration.light_rays import gauge_points, locate_lights
    from lightstage.calibration.probe import fit_balls, load_probe, probe_rays

    stage = capture.stage
    nominal = stage.light_positions_rig()
    intr_K = {c: K for c, (K, _) in intr.items()}
    K_proc = processed_intrinsics(stage, intr_K)
    light_sigma = config.light_prior_sigma_mm / 1000.0
    found = find_bulbs(work, capture, _rig_poses(reg), nominal, intr_K) if config.observe_bulbs else None
    probe = load_probe(work, capture) if config.use_probe else None

    def rays_of(reg: Any, for_gauge: bool = False) -> tuple[list, dict[str, Any] | None]:
        rays = bulb_rays(found.sightings, _rig_poses(reg), K_proc, config.bulb_pixel_sigma) if found else []
        if probe is None:
            return rays, None
        more, report = probe_rays(
            probe,
            _rig_poses(reg),
            intr,
            config.probe_pixel_sigma,
            config.probe_rotation_sigma_deg,
            config.probe_distance_sigma_mm,
            nominal_lights=nominal if config.probe_refine_distances else None,
            light_sigma_mm=config.light_prior_sigma_mm,
            keep_distance_sigma=for_gauge,
        )
        if scale_prior is not None:
            report["gauge_scale_prior"] = {
                "metres_per_sfm_unit": scale_prior[0],
                "relative_sigma": scale_prior[1],
            }
        return rays + more, report

    scale_prior = None
    if probe is not None and config.probe_scale:
        # The ball's known radius measures the rig's metric scale far better than the drawings' camera
        # positions can (their tolerance over the rig's size): refit the gauge with it.
        balls = fit_balls(probe, _rig_poses(reg), intr)
        if np.isfinite(balls.scale_ratio_sigma) and len(balls.cones) >= 3:
            rel = float(
                np.hypot(
                    balls.scale_ratio_sigma / balls.scale_ratio,
                    config.probe_radius_sigma_mm / 1e3 / probe.radius_m,
                )
            )
            scale_prior = (reg.rig_similarity.scale * balls.scale_ratio, max(rel, 1e-7))
            reg = register(None, scale_prior)
            log(
                f"probe: the ball's radius puts the rig's scale {1e3 * (balls.scale_ratio - 1):+.3f} per mille off "
                f"the drawings' fit (+- {1e3 * rel:.3f})"
            )

    def register_lights(extra_points: tuple | None) -> Any:
        return register(extra_points, scale_prior)

    rays, probe_report = rays_of(reg, for_gauge=True)
    gauge_lights: list[int] = []
    gauge_rejected: dict[str, float] = {}
    if config.lights_in_gauge and rays:
        # Observed lights are nominal points of the rig too: refit the gauge with them (their points, found in
        # the first fit's frame, are mapped back to the SfM rig frame the gauge starts from), then redo the rays.
        gauge_lights, pts, nom, sqrt_info = gauge_points(rays, nominal, mount_sigma_m=light_sigma)
        reg, gauge_lights, gauge_rejected = gauge_with_lights(
            register_lights,
            reg.rig_similarity.inverse().apply(pts),
            gauge_lights,
            nom,
            sqrt_info,
            config.light_gauge_max_sigma,
        )
    rays, probe_report = rays_of(reg)
    est = locate_lights(rays, nominal, prior_sigma_m=light_sigma)
    by_bulb = {li for li, src in est.sources.items() if any(s.startswith("bulb") for s in src)}
    by_probe = {li for li, src in est.sources.items() if any(s.startswith("probe") for s in src)}
    report: dict[str, Any] = {
        "num_lights": len(stage.lights),
        "num_observed": len(est.sources),
        "num_seen_as_bulbs": len(by_bulb),
        "num_seen_in_probe": len(by_probe),
        "num_in_gauge": len(gauge_lights),
        "gauge_rejected": gauge_rejected,
        "rays": len(rays),
        "rays_rejected": sum(est.rejected_rays.values()),
        "posterior_sigma_mm": {
            "mean": round(float(np.mean(list(est.sigma_mm.values()))), 3) if est.sigma_mm else None,
            "max": round(float(np.max(list(est.sigma_mm.values()))), 3) if est.sigma_mm else None,
        },
        "observed": {
            str(i): {
                "rays": len(src),
                "cameras_seeing_bulb": sorted(s.split()[1] for s in src if s.startswith("bulb")),
                "shift_from_nominal_mm": round(est.shift_mm[i], 3),
                "sigma_mm": round(est.sigma_mm[i], 3),
            }
            for i, src in est.sources.items()
        },
    }
    if found is not None:
        report["bulbs"] = {
            "candidate_light_cameras": found.candidates,
            "frames_read": found.frames_read,
            "unconfirmed_light_cameras": found.unconfirmed,
            "read_errors": found.read_errors[:20],
            "sightings": [
                {
                    "light": s.light,
                    "camera": s.camera,
                    "uv_processed": [round(s.uv[0], 3), round(s.uv[1], 3)],
                    "groups": s.groups,
                    "touching_mask": s.touching_mask,
                }
                for s in found.sightings
            ],
        }
        if found.read_errors:
            report["warnings"] = [
                f"bulbs: {len(found.read_errors)} processed frames unreadable (first: {found.read_errors[0]})"
            ]
    log(
        f"lights: {len(est.sources)}/{len(stage.lights)} observed ({len(by_bulb)} as bulbs, {len(by_probe)} "
        f"in the mirror-ball probe; {len(gauge_lights)} used in the gauge); "
        + ("the others at nominal rig positions" if len(est.sources) < len(stage.lights) else "")
    )
    report["_result"] = (reg, est.positions, gauge_lights)
    return report, probe_report


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
    lights_report, probe_report = _observe_lights(work, capture, config, intr, register, reg, log)
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
    points = colors = None
    rec = result.reconstruction
    if rec is not None and rec.num_points3D():
        xyz = np.stack([p.xyz for p in rec.points3D.values()])
        points = reg.world_from_sfm.apply(xyz)
        colors = np.stack([p.color for p in rec.points3D.values()])
    return calib, stats, (points, colors)


def run_calibrate(
    work: WorkDir, config: CalibrateConfig | None = None, client: Any = None, progress: bool = True
) -> dict[str, Any]:
    """Calibrate the capture of `work` (see the module doc); returns a small summary. `client` is unused
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
        points = colors = None
        if config.method == "nominal":
            calib = nominal_calibration(stage, intr if config.intrinsics else None)
            stats: dict[str, Any] = {"num_views": len(calib.views), "num_registered": len(calib.views)}
        else:
            calib, stats, (points, colors) = _sfm_calibration(work, capture, config, intr, log, progress)
        report["warnings"].extend(stats.pop("warnings", []))
        report["sfm" if config.method == "sfm" else "nominal"] = stats
        calib.save(work.calibration)
        write_colmap_model(calib, work.calibration_dir / "colmap", points, colors)
        write_transforms(calib, work.calibration_dir / "transforms.json", work)
        plot_layout(calib, work.calibration_dir / "layout.png")
        gt = GroundTruth.of(capture.root).geometry
        if gt.is_file():
            from lightstage.calibration.evaluate import compare_to_truth

            truth = Calibration.load(gt)
            report["ground_truth"] = compare_to_truth(calib, truth, _light_floor(capture, truth))
            probe_truth = GroundTruth.of(capture.root).probe
            if "probe" in stats and probe_truth.is_file():
                report["ground_truth"]["probe_ball_centre_error_mm"] = _ball_centre_errors(
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
