"""The gauge refit with observed lights (calibration.observed_lights.gauge_with_lights): exact lights keep the exact gauge,
a light far off its nominal position (a wrong disc or a bad camera) is dropped instead of tilting the world."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from lightstage.calibration.observed_lights import gauge_with_lights
from lightstage.calibration.register import Similarity, register_rig
from lightstage.cameras import camera_center
from lightstage.capture.presets import make_stage


def test_gauge_with_lights_drops_a_light_far_off_nominal():
    stage = make_stage("t", num_cameras=20, num_lights=40, width=512, height=340, camera_distance=1.1)
    rng = np.random.default_rng(3)
    S = Similarity(1.7, Rotation.random(random_state=rng).as_matrix(), rng.normal(size=3))  # SfM = S(stage)
    sensor_from_rig = {c.id: S.transform_pose(c.R, c.t) for c in stage.cameras}
    rig_from_world = {stage.group_names[0]: (np.eye(3), np.zeros(3))}
    nominal_centres = {c.id: camera_center(c.R, c.t) for c in stage.cameras}

    def register(extra):
        return register_rig(
            sensor_from_rig,
            rig_from_world,
            nominal_centres,
            stage.group_names[:1],
            nominal_rotations={c.id: c.R for c in stage.cameras},
            rotation_sigma_deg=0.2,
            extra_points=extra,
        )

    nominal = stage.light_positions_rig()[:5]
    true = nominal.copy()
    true[2] += [0.03, -0.02, 0.01]  # 37 mm off: ~12 sigma
    sqrt_info = np.broadcast_to(np.eye(3) / 0.003, (5, 3, 3))
    reg, used, rejected = gauge_with_lights(
        register, S.apply(true), [10, 11, 12, 13, 14], nominal, sqrt_info, 4.0
    )
    assert used == [10, 11, 13, 14] and list(rejected) == ["12"] and rejected["12"] > 4.0
    # The remaining data are exact: the gauge is the exact inverse of S.
    assert reg.rig_similarity.scale == pytest.approx(1 / S.scale, rel=1e-9)
    np.testing.assert_allclose(reg.rig_similarity.R, S.R.T, atol=1e-9)
    # Nothing to drop: every light is used, one fit.
    reg, used, rejected = gauge_with_lights(
        register, S.apply(nominal), [1, 2, 3, 4, 5], nominal, sqrt_info, 4.0
    )
    assert used == [1, 2, 3, 4, 5] and rejected == {}


def test_a_measured_scale_overrules_the_drawings_scale():
    """Camera centres off their drawn positions leave the gauge's scale off by their tolerance over the rig's
    size; a scale measured by a known length (the probe ball) with a small std wins, a vague one does not."""
    from lightstage.calibration.register import fit_gauge

    stage = make_stage("t", num_cameras=20, num_lights=4, width=512, height=340, camera_distance=1.1)
    rng = np.random.default_rng(5)
    nominal = np.stack([camera_center(c.R, c.t) for c in stage.cameras])
    true = nominal + 0.003 * rng.normal(size=nominal.shape)
    S = Similarity(0.6, Rotation.random(random_state=rng).as_matrix(), rng.normal(size=3))
    src = S.apply(true)  # SfM sees the true rig
    free = fit_gauge(src, nominal)
    assert abs(free.scale * S.scale - 1) > 1e-4  # the drawings alone: scale off by ~1e-3
    measured = fit_gauge(src, nominal, scale_prior=(1 / S.scale, 1e-6))
    assert measured.scale * S.scale == pytest.approx(1, abs=3e-6)
    vague = fit_gauge(src, nominal, scale_prior=(1 / S.scale, 1.0))
    assert vague.scale == pytest.approx(free.scale, rel=1e-5)
