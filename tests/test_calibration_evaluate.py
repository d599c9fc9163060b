"""Calibration errors against ground truth: the object reprojection shift measures what pose errors do to the
model's pixels, independent of the gauge, and discounts the rotation/shift pair a narrow camera cannot see."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from lightstage.calibration.evaluate import (
    box_grid,
    compare_to_truth,
    reprojection_shift_px,
    true_object_points,
)
from lightstage.calibration.register import Similarity
from lightstage.cameras import camera_center, look_at
from lightstage.errors import LightstageError
from lightstage.records.calibration import Calibration
from lightstage.records.ground_truth import GroundTruth

F = 518.4  # the demo's processed focal length (px)
K = np.array([[F, 0.0, 96.0], [0.0, F, 64.0], [0.0, 0.0, 1.0]])
OBJECT = box_grid([-0.06, -0.06, -0.06], [0.06, 0.06, 0.06])
IDENTITY = Similarity(1.0, np.eye(3), np.zeros(3))


def test_box_grid_spans_the_box():
    g = box_grid([0, 1, 2], [1, 2, 4], n=3)
    assert g.shape == (27, 3)
    np.testing.assert_allclose(g.min(0), [0, 1, 2])
    np.testing.assert_allclose(g.max(0), [1, 2, 4])


def test_shift_is_zero_for_the_true_pose_in_any_gauge():
    R, t = look_at([1.1, 0.0, 0.3], [0.0, 0.0, 0.0])
    sim = Similarity(1.7, Rotation.from_rotvec([0.3, -0.2, 0.9]).as_matrix(), np.array([0.4, -1.0, 2.0]))
    # the same camera, in a frame that the similarity maps to the truth's
    R_est, t_est = sim.inverse().transform_pose(R, t)
    np.testing.assert_allclose(reprojection_shift_px(OBJECT, K, R_est, t_est, R, t, sim), 0.0, atol=1e-9)


def test_shift_discounts_the_rotation_a_narrow_camera_cannot_see():
    """A 0.13 deg camera rotation shifts the object by f * angle; the same angle about the object's centre (the
    camera also moves 2.5 mm sideways, as in a weakly constrained SfM run) shifts it ~30x less."""
    d = 1.1
    R, t = look_at([d, 0.0, 0.0], [0.0, 0.0, 0.0])
    theta = np.deg2rad(0.13)
    pan = Rotation.from_rotvec([0.0, theta, 0.0]).as_matrix()  # about the camera's vertical axis
    R_pure, t_pure = pan @ R, -(pan @ R) @ camera_center(R, t)  # turned in place
    pure = reprojection_shift_px(OBJECT, K, R_pure, t_pure, R, t, IDENTITY)
    # about the world's vertical through the object
    orbit_z = Rotation.from_rotvec([0.0, 0.0, theta]).as_matrix()
    R_orbit, t_orbit = R @ orbit_z.T, t  # turned by the same angle with its centre moved round the object
    orbit = reprojection_shift_px(OBJECT, K, R_orbit, t_orbit, R, t, IDENTITY)
    assert np.linalg.norm(camera_center(R_orbit, t_orbit) - camera_center(R, t)) == pytest.approx(
        d * theta, rel=1e-3
    )
    assert pure.mean() == pytest.approx(F * theta, rel=0.05)
    assert orbit.mean() < pure.mean() / 10


def test_compare_to_truth_reports_the_shift_and_the_worst_view(tiny_capture: Path):
    gt = GroundTruth.of(tiny_capture)
    truth = Calibration.load(gt.geometry)
    points = true_object_points(gt.scene)
    assert points is not None and points.shape == (125, 3)
    same = compare_to_truth(truth, truth, object_points=points)["aligned"]["object_reprojection_shift_px"]
    assert same["max"] == pytest.approx(0.0, abs=1e-6)
    view = sorted(truth.views)[1]
    v = truth.views[view]
    dR = Rotation.from_rotvec([np.deg2rad(0.2), 0.0, 0.0]).as_matrix()
    bent = dataclasses.replace(
        truth, views={**truth.views, view: dataclasses.replace(v, R=dR @ v.R, t=dR @ v.t)}
    )
    shift = compare_to_truth(bent, truth, object_points=points)["aligned"]["object_reprojection_shift_px"]
    assert shift["worst_view"] == str(view)
    assert shift["max"] > 0.1 and shift["median"] < shift["max"] / 10
    assert "object_reprojection_shift_px" not in compare_to_truth(bent, truth)["aligned"]


def test_object_points_name_a_bad_scene_file(tmp_path: Path):
    assert true_object_points(tmp_path / "absent.json") is None
    bad = tmp_path / "scene.json"
    bad.write_text(json.dumps({"body": []}))
    with pytest.raises(LightstageError, match="scene.json: no readable object_bbox"):
        true_object_points(bad)
