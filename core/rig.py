"""Turntable convention, in one place: how a group's yaw moves the camera+light rig in the world frame.

The object is static in the world frame. For group g the rig is rotated by yaw psi_g about the turntable
axis (a unit direction through a point; nominally +z through the origin). A rig-frame point x_r lands at
x_w = R_g x_r + t_g with R_g = rot(axis, psi_g) and t_g = a - R_g a.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lightstage.cameras import rotation_axis_angle


@dataclass(frozen=True)
class TurntableAxis:
    """The turntable axis in world coordinates: unit `direction` through `point` (metres)."""

    direction: tuple[float, float, float] = (0.0, 0.0, 1.0)
    point: tuple[float, float, float] = (0.0, 0.0, 0.0)


def group_transform(yaw_deg: float, axis: TurntableAxis = TurntableAxis()) -> tuple[np.ndarray, np.ndarray]:
    """(R_g, t_g) mapping rig-frame points into the world frame for a group at `yaw_deg`."""
    R = rotation_axis_angle(np.asarray(axis.direction), np.deg2rad(yaw_deg))
    a = np.asarray(axis.point, dtype=np.float64)
    return R, a - R @ a


def camera_pose_in_world(
    R_rig: np.ndarray, t_rig: np.ndarray, yaw_deg: float, axis: TurntableAxis = TurntableAxis()
) -> tuple[np.ndarray, np.ndarray]:
    """World-to-camera (R, t) of a camera whose rig-frame world-to-camera pose is (R_rig, t_rig)."""
    Rg, tg = group_transform(yaw_deg, axis)
    R = np.asarray(R_rig) @ Rg.T
    return R, np.asarray(t_rig) - R @ tg


def light_position_in_world(
    p_rig: np.ndarray, yaw_deg: float, axis: TurntableAxis = TurntableAxis()
) -> np.ndarray:
    """World position(s) (..., 3) of rig-frame light position(s) for a group at `yaw_deg`."""
    Rg, tg = group_transform(yaw_deg, axis)
    return np.asarray(p_rig) @ Rg.T + tg
