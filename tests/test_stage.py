"""Stage description: the paper preset's geometry, YAML round-trip, validation messages."""

from __future__ import annotations

import copy

import numpy as np
import pytest
import yaml

from lightstage.capture.presets import paper_stage, stage_preset
from lightstage.capture.stage import load_stage, stage_from_dict
from lightstage.errors import LightstageError


@pytest.fixture(scope="module")
def paper():
    return paper_stage()


def test_paper_counts(paper):
    assert len(paper.cameras) == 20
    assert len(paper.lights) == 331
    assert [g.name for g in paper.groups] == ["000", "040", "080", "120", "160", "200", "240", "280", "320"]
    assert [g.yaw_deg for g in paper.groups] == list(range(0, 360, 40))
    assert (paper.width, paper.height) == (8192, 5464)
    assert paper.saturation == pytest.approx(4.4019)
    assert paper.num_frames == 59_580


def test_paper_lights_on_truncated_sphere(paper):
    p = paper.light_positions_rig()
    np.testing.assert_allclose(np.linalg.norm(p, axis=1), 1.5, atol=1e-12)
    assert (p[:, 2] >= -paper.centre_height).all(), "no light below the floor"
    assert p[:, 2].max() > 1.4  # reaches the zenith
    assert len(np.unique(np.round(p, 6), axis=0)) == 331


def test_paper_cameras_look_at_centre(paper):
    for g in paper.group_names:
        for cid in paper.camera_ids:
            cam = paper.view_camera(g, cid)
            centre_cam = cam.R @ np.zeros(3) + cam.t
            assert centre_cam[2] > 0  # centre in front of the camera
            np.testing.assert_allclose(centre_cam[:2], 0, atol=1e-9)  # on the optical axis
            np.testing.assert_allclose(np.linalg.norm(cam.center), 1.5, atol=1e-9)


def test_groups_rotate_rig_about_z(paper):
    c0 = paper.view_camera("000", "cam00").center
    c1 = paper.view_camera("040", "cam00").center
    ang = np.degrees(np.arctan2(c1[1], c1[0]) - np.arctan2(c0[1], c0[0])) % 360
    assert ang == pytest.approx(40.0)
    np.testing.assert_allclose(paper.light_positions_world("000"), paper.light_positions_rig())
    lw = paper.light_positions_world("080")
    np.testing.assert_allclose(lw[:, 2], paper.light_positions_rig()[:, 2])


def test_yaml_round_trip(paper, tmp_path):
    path = tmp_path / "stage.yaml"
    paper.save(path)
    again = load_stage(path)
    assert again.to_dict() == paper.to_dict()
    assert again.view_camera("120", "cam07").K.tolist() == paper.view_camera("120", "cam07").K.tolist()


@pytest.mark.parametrize(
    "mutate, message",
    [
        (
            lambda d: d["cameras"].append(copy.deepcopy(d["cameras"][0])),
            "cameras[20].id: duplicate id 'cam00'",
        ),
        (
            lambda d: d["lights"][5].update(position=[0.0, 0.0, -1.3]),
            "lights[5].position: z = -1.3000 m is below",
        ),
        (
            lambda d: d["cameras"][3]["pose"].update(R=[[1, 0, 0], [0, 2, 0], [0, 0, 1]]),
            "cameras[3] (cam03).pose.R",
        ),
        (lambda d: d["lights"][7].update(index=9), "lights[9].index: duplicate index 9"),
        (lambda d: d.update(lights=[]), "lights: must not be empty"),
        (lambda d: d["groups"][1].update(name=40), "groups[1].name: expected a string, got 40"),
        (lambda d: d["groups"][2].update(yaw_deg=400), "groups[2].yaw_deg: must be in [0, 360)"),
        (lambda d: d["resolution"].pop("width"), "resolution.width: missing"),
        (lambda d: d["cameras"][0]["intrinsics"].update(fx=-3.0), "focal lengths must be positive"),
        (lambda d: d["lights"][0].update(position=[1, 2]), "lights[0].position: expected shape (3,)"),
        (lambda d: d.update(saturation="high"), "saturation: expected a number, got 'high'"),
        (
            lambda d: d.update(sphere_radus=1.5),
            "unknown key 'sphere_radus' (did you mean 'sphere_radius'?)",
        ),
        (
            lambda d: d["cameras"][2]["pose"].update(T=[0, 0, 1]),
            "unknown key 'cameras[2].pose.T' (did you mean 'cameras[2].pose.t'?)",
        ),
    ],
)
def test_validation_messages_name_the_field(paper, mutate, message):
    data = copy.deepcopy(paper.to_dict())
    mutate(data)
    with pytest.raises(LightstageError) as err:
        stage_from_dict(data, "my/stage.yaml")
    assert str(err.value).startswith("my/stage.yaml: ")
    assert message in str(err.value)


def test_invalid_yaml_file(tmp_path):
    path = tmp_path / "stage.yaml"
    path.write_text("cameras: [\n")
    with pytest.raises(LightstageError, match="invalid YAML"):
        load_stage(path)
    with pytest.raises(LightstageError, match="cannot read"):
        load_stage(tmp_path / "missing.yaml")


def test_unknown_preset():
    with pytest.raises(LightstageError, match="unknown stage preset 'nope'"):
        stage_preset("nope")


def test_yaml_quoted_group_names(paper, tmp_path):
    path = tmp_path / "stage.yaml"
    paper.save(path)
    raw = yaml.safe_load(path.read_text())
    assert all(isinstance(g["name"], str) for g in raw["groups"])


def test_save_after_replace_with_numpy_axis(paper, tmp_path):
    """A stage edited in code (numpy floats in the axis and light positions) still saves as plain YAML."""
    import dataclasses

    from lightstage.rig import TurntableAxis

    direction = np.array([0.0, 0.01, 1.0]) / np.linalg.norm([0.0, 0.01, 1.0])
    axis = TurntableAxis(direction=tuple(direction), point=tuple(np.array([0.001, 0.0, 0.0])))
    edited = dataclasses.replace(paper, axis=axis)
    path = tmp_path / "stage.yaml"
    edited.save(path)
    again = load_stage(path)
    np.testing.assert_allclose(again.axis.point, [0.001, 0.0, 0.0])
    assert again.to_dict()["turntable_axis"] == edited.to_dict()["turntable_axis"]
