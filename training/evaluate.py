"""Evaluation: render every test image in chunks, score PSNR/SSIM (and LPIPS-VGG when its weights are local) on
the project tonemap, beside a constant-colour baseline, and write reports/eval.json plus side-by-side PNGs.

Exposure rule: one exposure per capture, chosen from the training targets (the 99th percentile of foreground
luminance maps to 1, `lightstage.tonemap.auto_exposure`), stored in the checkpoint and used for every image.
The baseline predicts the mean training colour (of the loader's rays) at every pixel.
"""

from __future__ import annotations

import time
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tqdm import tqdm

from lightstage.atomic import write_json_atomic
from lightstage.cameras import PinholeCamera, camera_rays
from lightstage.errors import LightstageError
from lightstage.tonemap import tonemap, tonemap_u8
from lightstage.training.config import EvalConfig
from lightstage.training.data import TestImage
from lightstage.training.metrics import image_metrics
from lightstage.training.model import RelightModel
from lightstage.workdir import WorkDir


@torch.no_grad()
def render_image(
    model: RelightModel, camera: PinholeCamera, light_direction: np.ndarray, chunk: int = 8192
) -> np.ndarray:
    """(H, W, 3) float32 HDR image rendered in chunks of rays (deterministic samples)."""
    device = model.centre.device
    o, d = camera_rays(camera)
    o_t = torch.from_numpy(o.astype(np.float32)).to(device)
    d_t = torch.from_numpy(d.astype(np.float32)).to(device)
    light = torch.as_tensor(np.asarray(light_direction, np.float32), device=device).reshape(1, 3)
    out = []
    for i in range(0, len(o_t), chunk):
        n = len(o_t[i : i + chunk])
        out.append(
            model(o_t[i : i + chunk], d_t[i : i + chunk], light.expand(n, 3), randomized=False)["rgb"].float()
        )
    return torch.cat(out).cpu().numpy().reshape(camera.height, camera.width, 3)


def side_by_side(
    pred: np.ndarray, target: np.ndarray, exposure: float, error_gain: float = 4.0
) -> np.ndarray:
    """uint8 (H, 3W, 3): prediction | target | error heat map (|tonemapped difference| x gain, inferno)."""
    import matplotlib

    err = np.abs(tonemap(pred, exposure) - tonemap(target, exposure)).mean(-1) * error_gain
    heat = (matplotlib.colormaps["inferno"](np.clip(err, 0, 1))[..., :3] * 255).round().astype(np.uint8)
    return np.concatenate([tonemap_u8(pred, exposure), tonemap_u8(target, exposure), heat], axis=1)


def evaluate_images(
    model: RelightModel,
    images: Iterable[TestImage],
    exposure: float,
    baseline_rgb: list[float],
    out_dir: Path | None = None,
    chunk: int = 8192,
    lpips_fn=None,
    progress: bool = False,
    total: int | None = None,
) -> dict[str, Any]:
    """Per-image and mean PSNR/SSIM(/LPIPS) of the model and of the constant baseline; PNGs into out_dir."""
    from lightstage.training.trainer import _write_png

    rows = []
    for img in tqdm(images, total=total, desc="eval", disable=not progress, unit="img"):
        t0 = time.perf_counter()
        pred = render_image(model, img.camera, img.light_direction, chunk)
        row: dict[str, Any] = {"name": img.name, **image_metrics(pred, img.target, exposure)}
        base = np.broadcast_to(np.asarray(baseline_rgb, np.float32), img.target.shape)
        bm = image_metrics(base, img.target, exposure)
        row.update(baseline_psnr=bm["psnr"], baseline_ssim=bm["ssim"])
        row["lpips"] = (
            float(lpips_fn(tonemap(pred, exposure), tonemap(img.target, exposure))) if lpips_fn else None
        )
        row["seconds"] = time.perf_counter() - t0
        if out_dir is not None:
            _write_png(Path(out_dir) / f"{img.name}.png", side_by_side(pred, img.target, exposure))
        rows.append(row)
    keys = ("psnr", "ssim", "baseline_psnr", "baseline_ssim") + (("lpips",) if lpips_fn else ())
    mean = {k: float(np.mean([r[k] for r in rows])) if rows else None for k in keys}
    return {
        "images": rows,
        "mean": mean,
        "count": len(rows),
        "exposure": exposure,
        "baseline_rgb": baseline_rgb,
        "lpips": "vgg" if lpips_fn else "unavailable",
    }


def run_eval(
    work: WorkDir,
    config: EvalConfig | None = None,
    client=None,
    progress: bool = True,
    checkpoint: Path | None = None,
    device: str = "cpu",
) -> dict[str, Any]:
    """Score the trained model on the test split in WORK/shards/test; writes reports/eval.json and eval PNGs.
    `config` is an EvalConfig (None: the one stored with the checkpoint). `client` is unused (rendering is GPU work)."""
    from lightstage.training.data_real import count_test_images, iter_test_images
    from lightstage.training.lpips import lpips_or_none
    from lightstage.training.trained import load_trained

    t0 = time.perf_counter()
    trained = load_trained(work, checkpoint, device)
    cfg = config if config is not None else trained.config.eval
    lpips_fn, lpips_note = lpips_or_none(cfg.lpips_weights, cfg.lpips_linear_weights, device)
    total = count_test_images(work)
    if total == 0:
        raise LightstageError(f"{work.shards_dir / 'test'}: no test images (run lightstage shard WORK)")
    limit = cfg.max_images or total
    images = (img for k, img in enumerate(iter_test_images(work)) if k < limit)
    result = evaluate_images(
        trained.model,
        images,
        trained.exposure,
        trained.baseline_rgb,
        work.eval_dir,
        cfg.chunk,
        lpips_fn,
        progress,
        min(limit, total),
    )
    result.update(
        stage="eval",
        checkpoint_step=trained.step,
        seconds=time.perf_counter() - t0,
        lpips_note=lpips_note,
        tonemap="sRGB(clip(exposure * hdr))",
        device=str(device),
    )
    write_json_atomic(work.report("eval"), result)
    return {"count": result["count"], "mean": result["mean"], "report": str(work.report("eval"))}
