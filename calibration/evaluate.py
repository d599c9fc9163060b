"""Errors of a calibration against ground truth (the simulator's `ground_truth/geometry.json`).

"raw" errors compare directly in the world frame of the conventions. The world frame of an estimate is fixed by
the nominal rig (see `register`), so raw errors include the unobservable gauge difference; "aligned" errors are
after the best similarity (Umeyama on all camera centres) from the estimate to the truth, i.e. the shape error.
Light positions are also reported against the floor set by using nominal rig-frame light positions (the truth
jitters them; nothing in the well-lit images observes it).

Pose errors in degrees and millimetres overstate what matters to the model: a narrow-field camera looking at a
small object barely constrains a rotation paired with a sideways shift that keeps the object's image still. The
"object reprojection shift" measures that directly: points of the true object box projected by the estimated
(aligned) and the true camera, distance in processed pixels.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from lightstage.calibration.register import Similarity, umeyama
from lightstage.cameras import camera_center, project
from lightstage.capture.layout import Capture
from lightstage.errors import LightstageError
from lightstage.records.calibration import Calibration
from lightstage.rig import light_position_in_world


def _stats(x: list[float] | np.ndarray) -> dict[str, float]:
    x = np.asarray(x, dtype=np.float64)
    return {"mean": float(x.mean()), "median": float(np.median(x)), "max": float(x.max())} if x.size else {}


def _rot_err_deg(Ra: np.ndarray, Rb: np.ndarray) -> float:
    return float(np.rad2deg(Rotation.from_matrix(np.asarray(Ra) @ np.asarray(Rb).T).magnitude()))


def _camera_errors(est: Calibration, truth: Calibration, sim: Similarity | None) -> dict[str, Any]:
    rot, cen = [], []
    for view, gt in truth.views.items():
        if view not in est.views:
            continue
        e = est.views[view]
        R, t = (e.R, e.t) if sim is None else sim.transform_pose(e.R, e.t)
        rot.append(_rot_err_deg(R, gt.R))
        cen.append(1000.0 * float(np.linalg.norm(camera_center(R, t) - camera_center(gt.R, gt.t))))
    return {"rotation_error_deg": _stats(rot), "camera_centre_error_mm": _stats(cen)}


def _light_errors(est: Calibration, truth: Calibration, sim: Similarity | None) -> dict[str, float]:
    errs = []
    for g, p_gt in truth.light_positions.items():
        if g not in est.light_positions:
            continue
        p = est.light_positions[g] if sim is None else sim.apply(est.light_positions[g])
        errs.append(1000.0 * np.linalg.norm(np.asarray(p) - np.asarray(p_gt), axis=1))
    return _stats(np.concatenate(errs)) if errs else {}


def _yaw_errors(est: Calibration, truth: Calibration) -> dict[str, Any]:
    per = {}
    for g, y in truth.yaws_deg.items():
        if g in est.yaws_deg:
            per[g] = float((est.yaws_deg[g] - y + 180.0) % 360.0 - 180.0)
    stats = _stats(np.abs(list(per.values()))) if per else {}
    return {**stats, "per_group": per}


def box_grid(box_min: Any, box_max: Any, n: int = 5) -> np.ndarray:
    """(n**3, 3) points on a regular grid spanning the box (corners included)."""
    axes = [np.linspace(lo, hi, n) for lo, hi in zip(box_min, box_max, strict=True)]
    return np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)


def reprojection_shift_px(
    points: np.ndarray,
    K: np.ndarray,
    R_est: np.ndarray,
    t_est: np.ndarray,
    R_true: np.ndarray,
    t_true: np.ndarray,
    sim: Similarity,
) -> np.ndarray:
    """Per point, the pixel distance between true world `points` seen by the true camera and the same points
    mapped into the estimate's frame (`sim` maps estimate -> truth) seen by the estimated camera."""
    in_est = sim.inverse().apply(points)
    return np.linalg.norm(project(in_est, K, R_est, t_est) - project(points, K, R_true, t_true), axis=-1)


def _object_shift(
    est: Calibration, truth: Calibration, sim: Similarity, points: np.ndarray
) -> dict[str, Any]:
    per_view = {}
    for view, gt in truth.views.items():
        if view in est.views:
            e = est.views[view]
            K = e.camera().K  # processed resolution: the model's pixels
            per_view[str(view)] = float(reprojection_shift_px(points, K, e.R, e.t, gt.R, gt.t, sim).mean())
    worst = max(per_view, key=per_view.get) if per_view else None
    return {**_stats(list(per_view.values())), "worst_view": worst}


def compare_to_truth(
    est: Calibration,
    truth: Calibration,
    light_floor: Calibration | None = None,
    object_points: np.ndarray | None = None,
) -> dict[str, Any]:
    """Errors of `est` against `truth`: raw and after the gauge-fixing similarity (see the module doc).

    `light_floor`: the truth's rig poses with nominal rig-frame lights, to report the unobservable part.
    `object_points`: world points of the true object (e.g. `box_grid` of its box), for the per-view mean
    object reprojection shift in processed pixels (aligned).
    """
    common = [v for v in truth.views if v in est.views]
    src = np.stack([camera_center(est.views[v].R, est.views[v].t) for v in common])
    dst = np.stack([camera_center(truth.views[v].R, truth.views[v].t) for v in common])
    sim = umeyama(src, dst)
    d_est, d_gt = np.asarray(est.axis.direction, float), np.asarray(truth.axis.direction, float)
    # Axis point error: distance between the two axis lines at the height of the scene centre (z = 0).
    a_est, a_gt = np.asarray(est.axis.point, float), np.asarray(truth.axis.point, float)
    p_est = a_est - (a_est[2] / d_est[2]) * d_est
    p_gt = a_gt - (a_gt[2] / d_gt[2]) * d_gt
    out: dict[str, Any] = {
        "num_views_compared": len(common),
        "raw": {
            **_camera_errors(est, truth, None),
            "light_position_error_mm": _light_errors(est, truth, None),
        },
        "aligned": {
            "similarity": {
                "scale": sim.scale,
                "rotation_deg": float(np.rad2deg(Rotation.from_matrix(sim.R).magnitude())),
                "translation_mm": float(1000.0 * np.linalg.norm(sim.t)),
            },
            **_camera_errors(est, truth, sim),
            "light_position_error_mm": _light_errors(est, truth, sim),
        },
        "yaw_error_deg": _yaw_errors(est, truth),
        "axis_direction_error_deg": float(np.rad2deg(np.arccos(np.clip(d_est @ d_gt, -1.0, 1.0)))),
        "axis_point_error_mm": float(1000.0 * np.linalg.norm(p_est - p_gt)),
    }
    if object_points is not None:
        out["aligned"]["object_reprojection_shift_px"] = _object_shift(est, truth, sim, object_points)
    if light_floor is not None:
        out["light_position_floor_mm"] = _light_errors(light_floor, truth, None)
    return out


def light_floor(capture: Capture, truth: Calibration) -> Calibration:
    """The truth's rig poses carrying the NOMINAL rig-frame lights: the best a rig-locked light model can do."""
    p_rig = capture.stage.light_positions_rig()
    lights = {g: light_position_in_world(p_rig, y, truth.axis) for g, y in truth.yaws_deg.items()}
    return Calibration("floor", {}, lights, truth.axis, truth.yaws_deg)


def true_object_points(scene_path: Path) -> np.ndarray | None:
    """`box_grid` of the simulator's true object box (scene.json `object_bbox`); None when the file is absent."""
    if not scene_path.is_file():
        return None
    try:
        box = json.loads(scene_path.read_text())["object_bbox"]
        return box_grid(np.asarray(box["min"], float), np.asarray(box["max"], float))
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise LightstageError(f"{scene_path}: no readable object_bbox ({e})") from None


def ball_centre_errors(probe_report: dict[str, Any], truth_path: Path) -> dict[str, float]:
    """Per probe position, the distance (mm) of the fitted ball centre from the true one (rig frame)."""
    try:
        truth = json.loads(truth_path.read_text())["positions"]
        return {
            pos: round(1000.0 * float(np.linalg.norm(np.subtract(c, truth[pos]["ball_centre_rig"]))), 3)
            for pos, c in probe_report["ball_centres_rig_m"].items()
        }
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise LightstageError(f"{truth_path}: unreadable ({e})") from None
