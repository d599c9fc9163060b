"""Image metrics, in one place: PSNR, SSIM (the field's: 11x11 Gaussian window, sigma 1.5, Wang et al. 2004,
through scikit-image) and LPIPS (training/lpips.py: `lpips` = VGG, what the paper's code reports, and
`lpips_alex`, the lpips package's default), scored in three conventions (CONVENTIONS) on the project's tonemap
(lightstage.tonemap) or the paper code's.

A test image's target outside its foreground mask is set to 0 before scoring (as the paper's code does and as
the training targets are); the prediction is scored as rendered. `full` keeps every pixel of the raw target.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping

import numpy as np
from skimage.metrics import structural_similarity

from lightstage.tonemap import paper_tonemap, tonemap

SSIM_SIGMA = 1.5  # Gaussian window; scikit-image truncates at 3.5 sigma -> radius 5 -> 11 x 11
SSIM_WINDOW = 11
# scikit-image's arguments for the field's SSIM on [0, 1] RGB (H, W, 3) images
SSIM_ARGS = {
    "gaussian_weights": True,
    "sigma": SSIM_SIGMA,
    "use_sample_covariance": False,
    "data_range": 1.0,
    "channel_axis": -1,
}

# key suffix -> what is compared (prediction vs target), in [0, 1] after the named tonemap
CONVENTIONS = {
    "": "masked, our tonemap: tonemap(pred) vs tonemap(target * mask); tonemap = sRGB(clip(exposure * hdr))",
    "_full": "full frame, our tonemap: tonemap(pred) vs tonemap(target), every pixel of the raw target",
    "_paper": "masked, the paper code's convention: paper_tonemap(pred) vs paper_tonemap(target * mask); "
    "paper_tonemap = sRGB(clip(log(1 + hdr), 0, 1)), no exposure",
}


def psnr(pred: np.ndarray, target: np.ndarray, data_range: float = 1.0) -> float:
    """10 log10(range^2 / MSE) over all pixels and channels (inf for identical images)."""
    mse = float(np.mean((np.asarray(pred, np.float64) - np.asarray(target, np.float64)) ** 2))
    return float("inf") if mse == 0 else 10.0 * np.log10(data_range**2 / mse)


def ssim_map(pred: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Per-pixel SSIM of [0, 1] RGB images, channels averaged, (H, W): the field's window (module docstring),
    population covariances, K1 0.01, K2 0.03; positions within SSIM_WINDOW // 2 of the border are padding."""
    _, smap = structural_similarity(
        np.asarray(pred, np.float64), np.asarray(target, np.float64), full=True, **SSIM_ARGS
    )
    return smap.mean(axis=-1)


def ssim_valid(shape: tuple[int, ...]) -> np.ndarray:
    """(H, W) bool: the window positions SSIM averages over (not within SSIM_WINDOW // 2 of the border)."""
    pad = (SSIM_WINDOW - 1) // 2
    valid = np.zeros(shape[:2], bool)
    valid[pad : shape[0] - pad, pad : shape[1] - pad] = True
    return valid


def ssim(pred: np.ndarray, target: np.ndarray) -> float:
    """SSIM of [0, 1] RGB images as NeRF/3DGS papers report it: Gaussian 11x11 window (sigma 1.5), population
    covariances, K1 0.01, K2 0.03, the mean over the valid (unpadded) window positions, channels averaged."""
    return float(
        structural_similarity(np.asarray(pred, np.float64), np.asarray(target, np.float64), **SSIM_ARGS)
    )


def image_metrics(pred_hdr: np.ndarray, target_hdr: np.ndarray, exposure: float) -> dict[str, float]:
    """PSNR and SSIM of two linear HDR images after tonemap(exposure) (no mask applied here)."""
    p, t = tonemap(pred_hdr, exposure), tonemap(target_hdr, exposure)
    return {"psnr": psnr(p, t), "ssim": ssim(p, t)}


def masked(target: np.ndarray, mask: np.ndarray | None) -> np.ndarray:
    """The target with 0 outside the (H, W) foreground mask (unchanged without a mask)."""
    if mask is None:
        return np.asarray(target)
    return np.where(np.asarray(mask, bool)[..., None], target, 0).astype(np.asarray(target).dtype)


def convention_images(
    pred: np.ndarray,
    target: np.ndarray,
    mask: np.ndarray | None,
    exposure: float,
    pred_full: np.ndarray | None = None,
) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """CONVENTIONS suffix -> (prediction, target) in [0, 1]. `pred_full`: the prediction scored in the full-frame
    convention (default `pred`; the ceiling scores the unmasked clean render there)."""
    tm = masked(target, mask)
    return {
        "": (tonemap(pred, exposure), tonemap(tm, exposure)),
        "_full": (tonemap(pred if pred_full is None else pred_full, exposure), tonemap(target, exposure)),
        "_paper": (paper_tonemap(pred), paper_tonemap(tm)),
    }


# LPIPS metric key -> training/lpips.py net: VGG (what the paper's code reports) and AlexNet (lpips' default)
LPIPS_NETS = {"lpips": "vgg", "lpips_alex": "alex"}
LPIPS_KEYS = tuple(LPIPS_NETS)
# key -> fn(pred, target in [0, 1]) -> distance, None for an image too small for the network
LpipsFns = Mapping[str, Callable[[np.ndarray, np.ndarray], float | None]]


def metric_names() -> tuple[str, ...]:
    """The metrics scored in every convention: psnr, ssim and the LPIPS keys."""
    return ("psnr", "ssim", *LPIPS_KEYS)


def scores(
    pred: np.ndarray,
    target: np.ndarray,
    mask: np.ndarray | None,
    exposure: float,
    lpips: LpipsFns | None = None,
    pred_full: np.ndarray | None = None,
) -> dict[str, float | None]:
    """psnr/ssim and every LPIPS key (LPIPS_KEYS; None where `lpips` has no function for it) with every
    CONVENTIONS suffix, of linear HDR images."""
    out: dict[str, float | None] = {}
    fns = lpips or {}
    for suffix, (p, t) in convention_images(pred, target, mask, exposure, pred_full).items():
        out[f"psnr{suffix}"] = psnr(p, t)
        out[f"ssim{suffix}"] = ssim(p, t)
        for key in LPIPS_KEYS:
            out[f"{key}{suffix}"] = fns[key](p, t) if key in fns else None
    return out


def ceiling_scores(
    clean: np.ndarray,
    target: np.ndarray,
    mask: np.ndarray | None,
    exposure: float,
    lpips: LpipsFns | None = None,
) -> dict[str, float | None]:
    """What a perfect prediction scores: the noise-free render of the frame, 0 outside the mask where the
    target is masked (the best a model trained on masked targets can do), the whole render in `full`."""
    return scores(masked(clean, mask), target, mask, exposure, lpips, pred_full=clean)
