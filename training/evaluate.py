"""Evaluation: render every test image in chunks and score it (training/metrics.py) beside a constant-colour
baseline and the ceiling (training/ceiling.py); write reports/eval.json and labelled side-by-side PNGs.

Keys of every per-image row and of `mean` (means over images; None where no image has the figure):
`psnr`, `ssim`, `lpips` (VGG, as the paper's code reports it) and `lpips_alex` (AlexNet) against the target
with 0 outside the foreground mask, in the project tonemap (the headline figures); the same with `_full` (every
pixel of the raw target) and `_paper` (the paper code's convention, sRGB(log(1 + hdr)), masked); `baseline_*`
for the constant colour (PSNR, SSIM) and `ceiling_*` for a perfect prediction (noise-free render; simulated
captures only). LPIPS is None for images under 32 px a side. `paper_protocol`: the `_paper` figures laid out
as the paper's Tables 1 and 2 (PSNR, SSIM x 100, LPIPS), each beside its ceiling.
`psnr_unflagged`, `ssim_unflagged`: the headline figures without the frame's flare and bulb pixels, beside
`flagged_fraction` and `backlit` per image (training/flagged.py); `backlit` in the report holds the means over the
back-lit test images alone (the light behind the object as seen from the camera).

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
from tqdm import tqdm

from lightstage.atomic import write_json_atomic
from lightstage.errors import LightstageError
from lightstage.executor import Executor
from lightstage.records.shards import TestImage
from lightstage.tonemap import tonemap, tonemap_u8
from lightstage.training.ceiling import CleanRenders
from lightstage.training.config import EvalConfig
from lightstage.training.flagged import flag_scores
from lightstage.training.inference import render_image
from lightstage.training.metrics import (
    CONVENTIONS,
    LPIPS_KEYS,
    LPIPS_NETS,
    LpipsFns,
    ceiling_scores,
    metric_names,
    scores,
)
from lightstage.training.model import RelightModel
from lightstage.workdir import WorkDir


def side_by_side(
    pred: np.ndarray, target: np.ndarray, exposure: float, error_gain: float = 4.0
) -> np.ndarray:
    """uint8 (H, 3W, 3): prediction | target | error heat map (|tonemapped difference| x gain, inferno).
    Evaluation passes the masked target (what it scores against)."""
    import matplotlib

    err = np.abs(tonemap(pred, exposure) - tonemap(target, exposure)).mean(-1) * error_gain
    heat = (matplotlib.colormaps["inferno"](np.clip(err, 0, 1))[..., :3] * 255).round().astype(np.uint8)
    return np.concatenate([tonemap_u8(pred, exposure), tonemap_u8(target, exposure), heat], axis=1)


def _mean(rows: list[dict[str, Any]], key: str) -> float | None:
    vals = [r[key] for r in rows if isinstance(r.get(key), int | float)]
    return float(np.mean(vals)) if vals else None


def evaluate_images(
    model: RelightModel,
    images: Iterable[TestImage],
    exposure: float,
    baseline_rgb: list[float],
    out_dir: Path | None = None,
    chunk: int = 8192,
    lpips: LpipsFns | None = None,
    progress: bool = False,
    total: int | None = None,
    clean: CleanRenders | None = None,
) -> dict[str, Any]:
    """Per-image and mean metrics (module docstring) of the model, the constant baseline and, where `clean`
    has the frame's noise-free render, the ceiling; prediction | masked target | error PNGs into out_dir."""
    from lightstage.frames import write_image

    rows = []
    for img in tqdm(images, total=total, desc="eval", disable=not progress, unit="img"):
        t0 = time.perf_counter()
        pred = render_image(model, img.camera, img.light_direction, chunk)
        row: dict[str, Any] = {"name": img.name, **scores(pred, img.target, img.mask, exposure, lpips)}
        base = np.broadcast_to(np.asarray(baseline_rgb, np.float32), img.target.shape)
        for k, v in scores(base, img.target, img.mask, exposure).items():
            if not k.startswith("lpips"):
                row[f"baseline_{k}"] = v
        ref = clean.get(img.frame, (img.camera.width, img.camera.height)) if clean is not None else None
        perfect = ceiling_scores(ref, img.target, img.mask, exposure, lpips) if ref is not None else {}
        row.update({f"ceiling_{k}": perfect.get(k) for k in scores_keys()})
        row.update(flag_scores(pred, img, exposure))
        row["masked"] = img.mask is not None
        row["seconds"] = time.perf_counter() - t0
        if out_dir is not None:
            write_image(Path(out_dir) / f"{img.name}.png", side_by_side(pred, img.masked_target, exposure))
        rows.append(row)
    keys = [k for k in (rows[0] if rows else {}) if k not in ("name", "masked", "seconds", "backlit")]
    mean = {k: _mean(rows, k) for k in keys}
    backlit = [r for r in rows if r.get("backlit")]
    return {
        "images": rows,
        "mean": mean,
        "count": len(rows),
        "backlit": {"count": len(backlit), "mean": {k: _mean(backlit, k) for k in keys}},
        "masked_count": sum(r["masked"] for r in rows),
        "ceiling_count": sum(r["ceiling_psnr"] is not None for r in rows),
        "exposure": exposure,
        "baseline_rgb": baseline_rgb,
        "lpips": {k: LPIPS_NETS[k] for k in LPIPS_KEYS if k in (lpips or {})},
        "paper_protocol": paper_protocol(mean, len(rows)),
        "conventions": {f"<metric>{k}": v for k, v in CONVENTIONS.items()},
    }


def scores_keys() -> list[str]:
    """The metric keys of one convention set: psnr, ssim and the LPIPS keys with every CONVENTIONS suffix."""
    return [f"{m}{s}" for s in CONVENTIONS for m in metric_names()]


# The paper's Tables 1 and 2: metric label, `mean` key (the paper code's convention), scale (SSIM in percent).
PAPER_PROTOCOL_ROWS = (
    ("PSNR (dB, higher is better)", "psnr_paper", 1.0),
    ("SSIM x 100 (higher is better)", "ssim_paper", 100.0),
    ("LPIPS VGG (lower is better)", "lpips_paper", 1.0),
    ("LPIPS AlexNet (lower is better)", "lpips_alex_paper", 1.0),
)


def paper_protocol(mean: dict[str, float | None], count: int) -> dict[str, Any]:
    """The test-split means in the paper code's convention as the rows of the paper's Tables 1-2, each beside
    its ceiling (what a perfect prediction scores on the same images; None without noise-free renders)."""

    def scaled(v: float | None, k: float) -> float | None:
        return None if v is None else v * k

    return {
        "convention": CONVENTIONS["_paper"],
        "split": "test",
        "images": count,
        "rows": [
            {
                "metric": label,
                "key": key,
                "ours": scaled(mean.get(key), k),
                "ceiling": scaled(mean.get(f"ceiling_{key}"), k),
            }
            for label, key, k in PAPER_PROTOCOL_ROWS
        ],
    }


def run_eval(
    work: WorkDir,
    config: EvalConfig | None = None,
    executor: Executor | None = None,
    progress: bool = True,
    checkpoint: Path | None = None,
    device: str = "cpu",
) -> dict[str, Any]:
    """Score the trained model on the test split in WORK/shards/test; writes reports/eval.json and eval PNGs.
    `config` is an EvalConfig (None: the one stored with the checkpoint). `executor` is unused (rendering is GPU work)."""
    from lightstage.training.inference import load_trained
    from lightstage.training.inputs import count_test_images, iter_test_images
    from lightstage.training.lpips import lpips_fns

    t0 = time.perf_counter()
    trained = load_trained(work, checkpoint, device)
    cfg = config if config is not None else trained.config.eval
    lpips, lpips_note = (
        lpips_fns(LPIPS_NETS, device) if cfg.lpips else ({}, "not computed (eval.lpips: false)")
    )
    clean, ceiling_note = CleanRenders.find(work)
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
        lpips,
        progress,
        min(limit, total),
        clean,
    )
    if clean is not None and result["ceiling_count"] < result["count"]:
        ceiling_note += (
            f"; {result['count'] - result['ceiling_count']} test image(s) have none (ceiling_* None there)"
        )
    result.update(
        stage="eval",
        checkpoint_step=trained.step,
        seconds=time.perf_counter() - t0,
        lpips_note=lpips_note,
        ceiling=ceiling_note,
        mask="the test image's foreground mask (shards/test/*.npz `mask`, from preprocess); target = 0 outside",
        tonemap="sRGB(clip(exposure * hdr)); `_paper` keys: sRGB(clip(log(1 + hdr), 0, 1))",
        ssim="Gaussian 11x11 window, sigma 1.5 (skimage gaussian_weights, population covariance)",
        device=str(device),
    )
    write_json_atomic(work.report("eval"), result)
    return {"count": result["count"], "mean": result["mean"], "report": str(work.report("eval"))}
