"""The true stage of a simulated capture: the nominal stage.yaml geometry plus seeded jitter of every camera,
light, the turntable axis and the yaws (what calibration must recover; saved as ground_truth/geometry.json)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lightstage.cameras import PinholeCamera, rotation_axis_angle
from lightstage.capture.stage import Stage
from lightstage.rig import TurntableAxis, camera_pose_in_world, light_position_in_world


@dataclass(frozen=True)
class Jitter:
    """Standard deviations of the seeded deviations of the true stage from the nominal one."""

    camera_rot_deg: float = 0.3
    camera_pos_m: float = 0.003
    light_pos_m: float = 0.003
    axis_tilt_deg: float = 0.35
    axis_offset_m: float = 0.003
    yaw_deg: float = 0.05


@dataclass(frozen=True)
class TrueGeometry:
    """The true (jittered) stage: rig-frame camera poses and light positions, turntable axis, yaws."""

    cameras: dict[str, tuple[np.ndarray, np.ndarray]]  # id -> (R_rig, t_rig)
    lights_rig: np.ndarray  # (L, 3)
    axis: TurntableAxis
    yaws_deg: dict[str, float]

    def view_camera(self, stage: Stage, group: str, camera: str) -> PinholeCamera:
        R, t = camera_pose_in_world(*self.cameras[camera], self.yaws_deg[group], self.axis)
        return PinholeCamera(stage.camera(camera).K, R, t, stage.width, stage.height)

    def light_positions(self, group: str) -> np.ndarray:
        return light_position_in_world(self.lights_rig, self.yaws_deg[group], self.axis)


def true_geometry(stage: Stage, seed: int, jitter: Jitter = Jitter()) -> TrueGeometry:
    """Seeded true geometry: per-camera rotation/position jitter, per-light jitter, tilted/offset axis, yaws."""
    rng = np.random.default_rng([seed, 1])
    cams = {}
    for c in stage.cameras:
        axis = rng.standard_normal(3)
        dR = rotation_axis_angle(axis, np.deg2rad(jitter.camera_rot_deg) * rng.standard_normal())
        centre = -c.R.T @ c.t + jitter.camera_pos_m * rng.standard_normal(3)
        R = dR @ c.R
        cams[c.id] = (R, -R @ centre)
    lights = stage.light_positions_rig() + jitter.light_pos_m * rng.standard_normal((len(stage.lights), 3))
    tilt_about = np.array([*rng.standard_normal(2), 0.0])
    tilt = np.deg2rad(jitter.axis_tilt_deg) * (0.5 + 0.5 * rng.random())
    direction = rotation_axis_angle(tilt_about, tilt) @ np.array([0.0, 0.0, 1.0])
    point = np.array([*(jitter.axis_offset_m * rng.standard_normal(2)), 0.0])
    yaws = {g.name: float(g.yaw_deg + jitter.yaw_deg * rng.standard_normal()) for g in stage.groups}
    # group 000 defines the world frame's orientation; keep its yaw exact
    yaws[stage.groups[0].name] = stage.groups[0].yaw_deg
    return TrueGeometry(cams, lights, TurntableAxis(tuple(direction), tuple(point)), yaws)
