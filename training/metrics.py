"""Image metrics on the project's one tonemap (lightstage.tonemap): PSNR, SSIM (scikit-image's reference
implementation) and LPIPS-VGG only when its weights are available locally."""

from __future__ import annotations

import numpy as np
from skimage.metrics import structural_similarity

from lightstage.tonemap import tonemap


def psnr(pred: np.ndarray, target: np.ndarray, data_range: float = 1.0) -> float:
    """10 log10(range^2 / MSE) over all pixels and channels (inf for identical images)."""
    mse = float(np.mean((np.asarray(pred, np.float64) - np.asarray(target, np.float64)) ** 2))
    return float("inf") if mse == 0 else 10.0 * np.log10(data_range**2 / mse)


def ssim(pred: np.ndarray, target: np.ndarray) -> float:
    """skimage structural_similarity on [0, 1] RGB images (7x7 uniform window, channels averaged)."""
    return float(structural_similarity(pred, target, channel_axis=-1, data_range=1.0))


def image_metrics(pred_hdr: np.ndarray, target_hdr: np.ndarray, exposure: float) -> dict[str, float]:
    """PSNR and SSIM of two linear HDR images after tonemap(exposure)."""
    p, t = tonemap(pred_hdr, exposure), tonemap(target_hdr, exposure)
    return {"psnr": psnr(p, t), "ssim": ssim(p, t)}
