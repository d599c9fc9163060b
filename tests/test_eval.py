"""Evaluation: metrics equal reference formulas/implementations on known images; run_eval on a work directory
with test images in the shard format writes reports/eval.json (model beside the constant baseline, LPIPS
unavailable without local weights) and side-by-side PNGs; the TrainedModel interface."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from skimage.metrics import peak_signal_noise_ratio, structural_similarity

from lightstage.errors import LightstageError
from lightstage.tonemap import tonemap
from lightstage.training.evaluate import run_eval
from lightstage.training.lpips import lpips_or_none
from lightstage.training.metrics import image_metrics, psnr, ssim
from lightstage.training.synthetic import SyntheticSphere
from lightstage.training.testing import micro_config
from lightstage.training.trained import load_trained
from lightstage.training.trainer import fit
from lightstage.workdir import WorkDir


def test_psnr_formula_and_reference():
    a = np.zeros((8, 8, 3))
    assert psnr(a + 0.1, a) == pytest.approx(20.0)  # MSE 0.01 -> 20 dB
    assert psnr(a, a) == float("inf")
    rng = np.random.default_rng(0)
    x, y = rng.random((16, 16, 3)), rng.random((16, 16, 3))
    assert psnr(x, y) == pytest.approx(peak_signal_noise_ratio(y, x, data_range=1.0))


def test_ssim_matches_skimage_and_bounds():
    rng = np.random.default_rng(1)
    x = rng.random((32, 32, 3)).astype(np.float32)
    y = np.clip(x + 0.1 * rng.normal(size=x.shape), 0, 1).astype(np.float32)
    assert ssim(x, y) == pytest.approx(structural_similarity(x, y, channel_axis=-1, data_range=1.0))
    assert ssim(x, x) == pytest.approx(1.0)
    assert ssim(x, y) < 1.0


def test_image_metrics_use_project_tonemap():
    rng = np.random.default_rng(2)
    hdr, ref = rng.random((16, 16, 3)) * 2, rng.random((16, 16, 3)) * 2
    m = image_metrics(hdr, ref, exposure=0.7)
    assert m["psnr"] == pytest.approx(psnr(tonemap(hdr, 0.7), tonemap(ref, 0.7)))
    assert m["ssim"] == pytest.approx(ssim(tonemap(hdr, 0.7), tonemap(ref, 0.7)))


def test_lpips_unavailable_without_local_weights(tmp_path):
    fn, note = lpips_or_none("", "", "cpu")
    assert fn is None and note.startswith("unavailable")
    fn, note = lpips_or_none(str(tmp_path / "vgg16.pth"), str(tmp_path / "vgg.pth"), "cpu")
    assert fn is None and "not found" in note


def _write_test_split(work: WorkDir, src: SyntheticSphere, n: int = 2) -> None:
    folder = work.shards_dir / "test"
    folder.mkdir(parents=True)
    records = []
    for img in src.test_images(n, size=16):
        c = img.camera
        np.savez(
            folder / f"{img.name}.npz",
            rgb=img.target.astype(np.float16),
            saturated=np.zeros((16, 16), bool),
            K=c.K,
            R=c.R,
            t=c.t,
            dist=np.zeros(5),
            width=np.int64(16),
            height=np.int64(16),
            light_direction=img.light_direction,
            light_position=img.light_direction * 1.5,
        )
        records.append({"file": f"test/{img.name}.npz"})
    (folder / "index.json").write_text(json.dumps({"images": records}))


def test_run_eval_and_trained_model_interface(tmp_path):
    work = WorkDir(tmp_path)
    src = SyntheticSphere(batch_size=64)
    with pytest.raises(LightstageError, match="no checkpoint"):
        load_trained(work)
    fit(micro_config(steps=4), src, work.train_dir, src.centre, src.scale, progress=False)
    with pytest.raises(LightstageError, match="no test images"):
        run_eval(work, progress=False)
    _write_test_split(work, src)
    summary = run_eval(work, progress=False)
    report = json.loads(work.report("eval").read_text())
    assert summary["count"] == report["count"] == 2
    assert report["lpips"] == "unavailable" and all(r["lpips"] is None for r in report["images"])
    for key in ("psnr", "ssim", "baseline_psnr", "baseline_ssim"):
        assert np.isfinite(report["mean"][key])
    assert sorted(p.name for p in work.eval_dir.glob("*.png")) == ["sphere_00.png", "sphere_01.png"]

    tm = load_trained(work)
    np.testing.assert_allclose(tm.centre, src.centre, rtol=1e-6)
    assert tm.scale == pytest.approx(src.scale)
    b = src.batch(0)
    rgb = tm.render_rays(b["origins"], b["directions"], b["light_directions"], chunk=16)
    assert rgb.shape == (64, 3) and not rgb.requires_grad and torch.all(rgb >= 0)
    dens = tm.density(torch.tensor([[0.1, -0.2, 0.3], [50.0, 0.0, 0.0]]))
    assert dens.shape == (2,) and dens[1] == 0
    img = tm.image_from_camera(src.camera(10.0, 5.0, size=8), np.array([0.0, 0.0, 1.0]))
    assert img.shape == (8, 8, 3) and img.dtype == np.float32


@pytest.mark.slow
def test_cli_train_and_eval_on_dataset_shards(tmp_path):
    """The real wiring: dataset fixture -> split -> shards -> `lightstage train` -> `lightstage eval`."""
    import yaml

    from lightstage.dataset.fixtures import make_synthetic_work
    from lightstage.dataset.shards import ShardConfig, run_shard
    from lightstage.dataset.split import SplitConfig, run_split
    from lightstage.pipelines.cli import main

    work, _ = make_synthetic_work(tmp_path)
    run_split(work, SplitConfig("paper"), progress=False)
    run_shard(work, ShardConfig(rays_per_image=64, rays_per_shard=256, workers=1), progress=False)
    cfg = micro_config(steps=3).to_dict()
    cfg["optim"]["batch_rays"] = 64
    cfg["eval"].update(every=2, images=1, max_images=2)
    (tmp_path / "micro.yaml").write_text(yaml.safe_dump(cfg))
    args = [str(work.root), "--config", str(tmp_path / "micro.yaml"), "--device", "cpu", "--no-progress"]
    assert main(["train", *args]) == 0
    report = json.loads(work.report("train").read_text())
    assert report["steps"] == 3 and np.isfinite(report["final_loss"])
    assert list((work.train_dir / "previews").glob("*.png"))
    assert main(["train", *args, "--steps", "6", "--stop-at", "4", "--eval-every", "1"]) == 0  # resumes at 3
    assert json.loads(work.report("train").read_text())["steps"] == 4  # stopped early, checkpointed
    assert main(["train", *args, "--steps", "6", "--eval-every", "1"]) == 0  # resumes from step 4
    report = json.loads(work.report("train").read_text())
    assert report["steps"] == 6 and report["train_seconds"] > 0
    evals = json.loads((work.train_dir / "log.json").read_text())["eval"]
    assert [e["step"] for e in evals] == [2, 4, 5, 6]  # every 2 up to 3, then every step: kept over resumes
    times = [e["train_seconds"] for e in evals]
    assert times == sorted(times) and times[0] > 0  # cumulative optimiser time, for time-to-PSNR
    assert main(["eval", str(work.root), "--device", "cpu", "--no-progress"]) == 0
    ev = json.loads(work.report("eval").read_text())
    assert ev["count"] == 2 and ev["lpips"] == "unavailable"
    assert main(["train", str(work.root), "--config", "nonexistent.yaml"]) == 2
