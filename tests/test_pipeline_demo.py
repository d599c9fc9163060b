"""The demo's report and envmap pieces on a hand-made work directory (the full demo is the CI smoke test)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from lightstage.capture.frames import write_image
from lightstage.pipelines.demo import montage, pick_envmap, sky_envmap, write_report
from lightstage.workdir import WorkDir


def test_sky_envmap_is_a_valid_latlong_map(tmp_path: Path) -> None:
    from lightstage.training.envmap import load_envmap, median_cut

    path = sky_envmap(tmp_path / "sky.exr")
    env = load_envmap(path, (32, 16))
    assert np.all(env.radiance >= 0) and env.radiance.max() > 10  # the sun
    lights = median_cut(env, 8)
    assert len(lights.directions) == 8


def test_pick_envmap_falls_back_to_the_synthetic_sky(tmp_path: Path, monkeypatch) -> None:
    monkeypatch.setenv("LIGHTSTAGE_ENVMAPS", str(tmp_path / "absent"))
    work = WorkDir.at(tmp_path / "work")
    assert pick_envmap(work) == work.root / "report" / "sky.exr"
    assert (work.root / "report" / "sky.exr").is_file()


def test_report_collects_pictures_and_metrics(tmp_path: Path) -> None:
    work = WorkDir.at(tmp_path / "work")
    rng = np.random.default_rng(0)
    for g, c in (("000", "cam00"), ("040", "cam01")):
        img = (rng.random((30, 40, 3)) * 255).astype(np.uint8)
        write_image(work.root / "preprocess" / "views" / g / c / "overlay.png", img)
    write_image(work.calibration_dir / "layout.png", np.zeros((50, 50, 3), np.uint8))
    write_image(work.eval_dir / "000_cam18_l005.png", np.full((20, 60, 3), 128, np.uint8))
    write_image(work.root / "relight" / "000_cam00_k016.png", np.full((20, 30, 3), 200, np.uint8))
    work.report("eval").parent.mkdir(parents=True, exist_ok=True)
    work.report("eval").write_text(
        json.dumps({"mean": {"psnr": 27.5, "ssim": 0.91}, "baseline": {"psnr": 15.0}})
    )
    work.report("calibration").write_text(
        json.dumps(
            {
                "ground_truth": {
                    "raw": {
                        "rotation_error_deg": {"mean": 0.027, "max": 0.041},
                        "camera_centre_error_mm": {"mean": 0.84, "max": 1.24},
                        "light_position_error_mm": {"mean": 1.24, "max": 3.03},
                    },
                    "yaw_error_deg": {"mean": 0.003, "max": -0.007, "per_group": {}},
                },
                "sfm": {"lights": {"num_observed": 16, "num_lights": 16, "num_seen_in_probe": 16}},
            }
        )
    )
    path = write_report(work, {"eval": 1.0}, {"envmap": "sky.exr", "tonemap": "srgb"}, 60.0, "tiny (seed 0)")
    text = path.read_text()
    assert "| light position (mm) | 1.24 | 3.03 |" in text and "| group yaw (deg) | 0.003 | 0.007 |" in text
    assert "Lights observed: 16 of 16 (0 as bulbs in view, 16 in the mirror-ball probe)." in text
    for pic in ("masks.png", "layout.png", "predictions.png", "relit_000_cam00_k016.png"):
        assert f"report/{pic}" in text
        assert (work.root / "report" / pic).is_file()
    assert "| mean.psnr | 27.5 |" in text and "| baseline.psnr | 15 |" in text


def test_montage_tiles_different_sizes() -> None:
    a = np.zeros((10, 20, 3), np.uint8)
    b = np.zeros((30, 10, 3), np.uint8)
    m = montage([a, b, a], columns=2, height=20)
    assert m.ndim == 3 and m.shape[0] == 2 * 24
