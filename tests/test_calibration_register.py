"""Registration of a recovered rig to the world frame: exact recovery of a synthetic axis, yaws and scale."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from lightstage.calibration.register import Similarity, fit_gauge, fit_turntable, register_rig, umeyama
from lightstage.cameras import camera_center
from lightstage.capture.presets import make_stage
from lightstage.errors import LightstageError
from lightstage.rig import TurntableAxis, camera_pose_in_world, group_transform


def _random_similarity(rng: np.random.Generator) -> Similarity:
    return Similarity(
        float(rng.uniform(0.2, 5.0)), Rotation.random(random_state=rng).as_matrix(), rng.normal(size=3)
    )


def _synthetic_sfm(stage, axis, yaws, sim, ref_cam="cam00"):
    """What SfM would return for a perfect rig: COLMAP-style rig frame = reference camera frame, world = sim(world)."""
    cams = {c.id: (np.asarray(c.R), np.asarray(c.t)) for c in stage.cameras}
    world_pose = {}
    for g, yaw in yaws.items():
        for cid, (R, t) in cams.items():
            world_pose[g, cid] = camera_pose_in_world(R, t, yaw, axis)
    sfm_pose = {k: sim.transform_pose(*v) for k, v in world_pose.items()}
    R_ref, t_ref = cams[ref_cam]
    # sensor_from_rig with the rig frame = the reference camera: cam_from_refcam = cam_from_rig * refcam_from_rig^-1.
    sensor_from_rig = {}
    for cid, (R, t) in cams.items():
        Rr = R @ R_ref.T
        sensor_from_rig[cid] = (Rr, sim.scale * (t - Rr @ t_ref))
    rig_from_world = {g: sfm_pose[g, ref_cam] for g in yaws}
    return sensor_from_rig, rig_from_world, world_pose


def test_umeyama_recovers_similarity():
    rng = np.random.default_rng(0)
    S = _random_similarity(rng)
    x = rng.normal(size=(12, 3))
    est = umeyama(x, S.apply(x))
    assert est.scale == pytest.approx(S.scale, rel=1e-12)
    np.testing.assert_allclose(est.R, S.R, atol=1e-12)
    np.testing.assert_allclose(est.t, S.t, atol=1e-12)
    np.testing.assert_allclose(S.inverse().apply(S.apply(x)), x, atol=1e-12)


@pytest.mark.parametrize("seed,rotation_sigma_deg", [(1, 0.0), (2, 0.0), (3, 0.2)])
def test_registration_recovers_axis_yaws_scale_exactly(seed, rotation_sigma_deg):
    rng = np.random.default_rng(seed)
    stage = make_stage("t", num_cameras=8, num_lights=12, width=512, height=340)
    direction = np.array([0.02, -0.015, 1.0])
    direction /= np.linalg.norm(direction)
    axis = TurntableAxis(tuple(direction), (0.004, -0.003, 0.0))
    # The point closest to the origin, as the fit reports it.
    a = np.asarray(axis.point) - (np.asarray(axis.point) @ direction) * direction
    yaws = {g.name: (0.0 if i == 0 else g.yaw_deg + rng.normal(0, 0.3)) for i, g in enumerate(stage.groups)}
    sim = _random_similarity(rng)
    sensor_from_rig, rig_from_world, world_pose = _synthetic_sfm(stage, axis, yaws, sim)
    nominal = {c.id: camera_center(c.R, c.t) for c in stage.cameras}
    reg = register_rig(
        sensor_from_rig,
        rig_from_world,
        nominal,
        stage.group_names,
        nominal_rotations={c.id: c.R for c in stage.cameras},
        rotation_sigma_deg=rotation_sigma_deg,
    )
    assert reg.rig_similarity.scale == pytest.approx(1.0 / sim.scale, rel=1e-9)
    assert reg.rig_fit_rms_m < 1e-9
    np.testing.assert_allclose(reg.turntable.axis.direction, direction, atol=1e-9)
    np.testing.assert_allclose(reg.turntable.axis.point, a, atol=1e-9)
    for g, y in yaws.items():
        assert reg.turntable.yaws_deg[g] == pytest.approx(y % 360.0, abs=1e-7)
        assert reg.turntable.rotation_misfit_deg[g] < 1e-7
        assert reg.turntable.translation_misfit_m[g] < 1e-9
        for cid in stage.camera_ids:
            R, t = reg.camera_pose(g, cid)
            np.testing.assert_allclose(R, world_pose[g, cid][0], atol=1e-9)
            np.testing.assert_allclose(t, world_pose[g, cid][1], atol=1e-9)
        # Lights locked to the rig.
        Rg, tg = group_transform(y, axis)
        p_rig = stage.light_positions_rig()
        np.testing.assert_allclose(reg.light_positions(g, p_rig), p_rig @ Rg.T + tg, atol=1e-9)


def test_fit_turntable_handles_yaws_past_180_degrees():
    axis = TurntableAxis((0.0, 0.0, 1.0), (0.01, 0.02, 0.0))
    from lightstage.calibration.register import Rigid

    motions = {f"{y:03d}": Rigid(*group_transform(y, axis)) for y in (0, 40, 170, 200, 320)}
    fit = fit_turntable(motions, "000")
    for g in motions:
        assert fit.yaws_deg[g] == pytest.approx(float(g), abs=1e-9)
    np.testing.assert_allclose(fit.axis.point, axis.point, atol=1e-12)


def test_gauge_with_orientations_beats_centres_alone():
    """Mounting errors (3 mm, ~0.2 deg per axis) on a 20-camera rig: fitting the nominal orientations as well as
    the centres pins the world frame's rotation better than Umeyama on the centres, on average."""
    stage = make_stage("t", num_cameras=20, num_lights=4, width=512, height=340, camera_distance=1.1)
    nominal_c = np.stack([camera_center(c.R, c.t) for c in stage.cameras])
    nominal_R = np.stack([c.R for c in stage.cameras])
    err_pts, err_ml = [], []
    for seed in range(12):
        rng = np.random.default_rng(seed)
        true_c = nominal_c + rng.normal(0, 0.003, nominal_c.shape)
        true_R = np.stack(
            [Rotation.from_rotvec(rng.normal(0, np.deg2rad(0.2), 3)).as_matrix() @ R for R in nominal_R]
        )
        S = _random_similarity(rng)  # recovered frame = S(true frame)
        src_c = S.apply(true_c)
        src_R = true_R @ S.R.T
        for fit, errs in (
            (umeyama(src_c, nominal_c), err_pts),
            (fit_gauge(src_c, nominal_c, src_R, nominal_R), err_ml),
        ):
            # Composite fit(S(x)) should be the identity; its rotation angle is the gauge error.
            errs.append(np.rad2deg(Rotation.from_matrix(fit.R @ S.R).magnitude()))
    assert np.mean(err_ml) < 0.5 * np.mean(err_pts)
    # Exact data: the fit is the exact inverse similarity.
    S = _random_similarity(np.random.default_rng(99))
    est = fit_gauge(S.apply(nominal_c), nominal_c, nominal_R @ S.R.T, nominal_R)
    assert est.scale == pytest.approx(1.0 / S.scale, rel=1e-9)
    np.testing.assert_allclose(est.R, S.R.T, atol=1e-9)


def test_gauge_with_observed_lights():
    """Observed lights as extra nominal points: exact data gives the exact similarity, also with a rank-2
    (across-the-ray) weight whose point may slide along its ray; with mounting errors the lights make the
    world frame better on average."""
    stage = make_stage("t", num_cameras=20, num_lights=40, width=512, height=340, camera_distance=1.1)
    nominal_c = np.stack([camera_center(c.R, c.t) for c in stage.cameras])
    nominal_R = np.stack([c.R for c in stage.cameras])
    nominal_l = stage.light_positions_rig()[:12]
    S = _random_similarity(np.random.default_rng(5))
    d = nominal_l - nominal_c[0]
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    L = np.stack([(np.eye(3) - np.outer(x, x)) / 0.003 for x in d])  # seen by cam00 only
    slid = nominal_l + 0.2 * d  # anywhere on the ray
    est = fit_gauge(
        S.apply(nominal_c),
        nominal_c,
        nominal_R @ S.R.T,
        nominal_R,
        src_extra=S.apply(slid),
        dst_extra=nominal_l,
        extra_sigma=L,
    )
    assert est.scale == pytest.approx(1.0 / S.scale, rel=1e-9)
    np.testing.assert_allclose(est.R, S.R.T, atol=1e-9)
    with pytest.raises(LightstageError, match="extra_sigma"):
        fit_gauge(nominal_c, nominal_c, src_extra=nominal_l, dst_extra=nominal_l, extra_sigma=L[:3])

    err_without, err_with = [], []
    for seed in range(12):
        rng = np.random.default_rng(seed)
        true_c = nominal_c + rng.normal(0, 0.003, nominal_c.shape)
        true_R = np.stack(
            [Rotation.from_rotvec(rng.normal(0, np.deg2rad(0.2), 3)).as_matrix() @ R for R in nominal_R]
        )
        true_l = nominal_l + rng.normal(0, 0.003, nominal_l.shape)
        S = _random_similarity(rng)
        src = (S.apply(true_c), nominal_c, true_R @ S.R.T, nominal_R)
        for extra, errs in (
            ({}, err_without),
            ({"src_extra": S.apply(true_l), "dst_extra": nominal_l}, err_with),
        ):
            fit = fit_gauge(*src, **extra, extra_sigma=0.003)
            errs.append(np.linalg.norm(fit.apply(S.apply(true_c)) - true_c, axis=1).mean())
    assert np.mean(err_with) < np.mean(err_without)
