"""The notebook API (lightstage.pipelines.api) takes plain paths and gives the pixels the commands write."""

from __future__ import annotations

import numpy as np
import pytest
from test_relight import FakeSphere, _sky, _work_with_calibration

from lightstage.frames import read_exr, write_exr
from lightstage.pipelines import api
from lightstage.training.relight import RelightConfig, run_relight


def test_relight_matches_the_relight_command(tmp_path):
    work = _work_with_calibration(tmp_path)
    write_exr(tmp_path / "env.exr", _sky(64, 128).astype(np.float32), half=False)
    config = RelightConfig.from_dict(
        {"envmap": str(tmp_path / "env.exr"), "lights": "8", "rotate_deg": 30.0, "out": str(tmp_path / "out")}
    )
    run_relight(work, config, progress=False, model=FakeSphere())
    written = read_exr(tmp_path / "out" / "000_cam00_k008.exr")
    got = api.relight(
        str(work.root), tmp_path / "env.exr", "000/cam00", lights=8, rotate_deg=30.0, model=FakeSphere()
    )
    assert got.shape == written.shape
    np.testing.assert_allclose(got, written, rtol=2e-3, atol=1e-4)  # the command writes half floats


def test_render_is_the_olat_of_the_calibrated_light(tmp_path):
    work = _work_with_calibration(tmp_path)
    calib = api.calibration(str(work.root))
    model = FakeSphere()
    got = api.render(str(work.root), "000/cam00", "000/1", model=model)
    from lightstage.ids import ViewId

    cam = calib.views[ViewId("000", "cam00")].camera()
    pos = np.asarray(calib.light_positions["000"][1], np.float64)
    direction = (pos - np.asarray(calib.scene_centre)) / np.linalg.norm(pos - np.asarray(calib.scene_centre))
    expected = model.image_from_camera(cam, direction)
    assert got.shape == expected.shape and expected.max() > 0
    np.testing.assert_allclose(got, expected, atol=1e-5)
    assert api.tonemap(got).dtype == np.uint8


def test_read_frame_and_mask_take_plain_paths(tmp_path):
    from support.fixtures import make_synthetic_work

    work, _ = make_synthetic_work(tmp_path)
    frame = next(iter(sorted(work.preprocess_dir.glob("frames/*/*/*.exr"))))
    group, camera, light = frame.parts[-3], frame.parts[-2], int(frame.stem)
    rgb, sat = api.read_frame(str(work.root), group, camera, light)
    assert rgb.dtype == np.float32 and rgb.shape[-1] == 3 and sat.shape == rgb.shape[:2]
    mask = api.read_mask(str(work.root), group, camera)
    assert mask.shape == rgb.shape[:2] and mask.dtype == bool and 0 < mask.mean() < 1


def test_missing_model_is_one_clear_error(tmp_path):
    from lightstage.errors import LightstageError

    with pytest.raises(LightstageError, match="checkpoint"):
        api.load_model(tmp_path / "nowhere")
