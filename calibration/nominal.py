"""The nominal calibration: cameras, lights, turntable axis and yaws exactly as stage.yaml describes them."""

from __future__ import annotations

import numpy as np

from lightstage.capture.stage import Stage
from lightstage.ids import ViewId
from lightstage.records.calibration import Calibration, ViewCalibration


def nominal_calibration(
    stage: Stage, intrinsics: dict[str, tuple[np.ndarray, np.ndarray]] | None = None
) -> Calibration:
    """Calibration from the stage description (optionally with fitted raw-resolution intrinsics per camera)."""
    views = {}
    for g in stage.groups:
        for c in stage.cameras:
            cam = stage.view_camera(g.name, c.id)
            K, dist = (cam.K, cam.dist) if intrinsics is None or c.id not in intrinsics else intrinsics[c.id]
            views[ViewId(g.name, c.id)] = ViewCalibration(
                np.asarray(K, float), cam.R, cam.t, stage.width, stage.height, np.asarray(dist, float)
            )
    return Calibration(
        method="nominal",
        views=views,
        light_positions={g.name: stage.light_positions_world(g.name) for g in stage.groups},
        axis=stage.axis,
        yaws_deg={g.name: float(g.yaw_deg) for g in stage.groups},
    )
