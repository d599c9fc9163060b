"""The demo's report and envmap pieces on a hand-made work directory (the full demo is the CI smoke test)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from lightstage.frames import read_image as read_png
from lightstage.frames import write_image
from lightstage.pipelines.demo import pick_envmap, sky_envmap
from lightstage.pipelines.demo_report import montage, write_report
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
    relit = {
        "envmap": "sky.exr",
        "tonemap": "srgb",
        "views": {"000_cam00": {"results": {"16": {"lights": 16}}}},
    }
    path = write_report(work, {"eval": 1.0}, relit, 60.0, "tiny (seed 0)")
    text = path.read_text()
    assert "Envmap: `sky.exr`, 16 median-cut lights; tonemap: srgb." in text
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


def test_report_shows_the_psnr_curve_the_ceiling_and_labelled_predictions(tmp_path: Path) -> None:
    from lightstage.pipelines.demo_report import COLUMNS, prediction_grid

    work = WorkDir.at(tmp_path / "work")
    names = ["000_cam19_003", "040_cam19_003", "080_cam18_003"]
    rows = []
    for k, name in enumerate(names):
        write_image(work.eval_dir / f"{name}.png", np.full((24, 96, 3), 60 * k, np.uint8))
        rows.append({"name": name, "psnr": 25.0 + k, "psnr_full": 22.0 + k, "ceiling_psnr": 40.0 + k})
    mean = {"psnr": 26.0, "ssim": 0.9, "ceiling_psnr": 41.0, "ceiling_ssim": 0.99, "baseline_psnr": 12.0}
    mean.update(psnr_full=23.0, psnr_paper=30.0, ceiling_psnr_full=33.0, lpips=0.12, lpips_alex=None)
    work.report("eval").parent.mkdir(parents=True, exist_ok=True)
    work.report("eval").write_text(
        json.dumps(
            {
                "images": rows,
                "mean": mean,
                "count": 3,
                "masked_count": 3,
                "ceiling_count": 3,
                "ceiling": "noise-free renders of the simulated capture",
                "conventions": {"<metric>": "masked"},
                "checkpoint_step": 40,
                "lpips_note": "LPIPS v0.1 (lpips = vgg, lpips_alex = alex)",
                "paper_protocol": {
                    "convention": "masked, the paper code's",
                    "split": "test",
                    "images": 3,
                    "rows": [
                        {"metric": "PSNR (dB, higher is better)", "ours": 30.0, "ceiling": 41.23},
                        {"metric": "SSIM x 100 (higher is better)", "ours": 95.04, "ceiling": None},
                        {"metric": "LPIPS VGG (lower is better)", "ours": 0.0921, "ceiling": 0.0113},
                    ],
                },
            }
        )
    )
    evals = [
        {"step": s, "psnr": 20.0 + s / 10, "psnr_full": 19.0, "images": names[:2]} for s in (10, 20, 30, 40)
    ]
    work.train_dir.mkdir(parents=True)
    (work.train_dir / "log.json").write_text(json.dumps({"train": [], "eval": evals}))
    text = write_report(work, {}, {}, 60.0, "tiny (seed 0)").read_text()
    assert "![test PSNR over training](report/psnr_curve.png)" in text
    assert (work.root / "report" / "psnr_curve.png").is_file()
    assert (
        "| masked, our tonemap | 26.00 | 0.9000 | 0.1200 | n/a | 41.00 | 0.9900 | n/a | n/a | 12.00 |" in text
    )
    assert "LPIPS: LPIPS v0.1 (lpips = vgg" in text
    assert "| PSNR (dB, higher is better) | 30.0 | 41.2 |" in text  # the paper-protocol table
    assert "| SSIM x 100 (higher is better) | 95.0 | n/a |" in text
    assert "| LPIPS VGG (lower is better) | 0.092 | 0.011 |" in text
    assert (
        "| full frame, our tonemap | 23.00 |" in text and "paper code's sRGB(log(1 + hdr)) | 30.00 |" in text
    )
    assert "000_cam19_003: masked PSNR 25.00 dB (ceiling 40.00)" in text
    grid = read_png(work.root / "report" / "predictions.png")
    assert grid.shape[1] == 160 * 4 and grid.shape[0] > 3 * 160  # panels enlarged to 160 px, captions between
    assert len(COLUMNS) == 3
    # captions are drawn: the strips above the panels are not blank
    g = prediction_grid([(np.zeros((24, 96, 3), np.uint8), "a caption")])
    assert (g[:26] < 128).any() and (g[26:48] < 128).any()
