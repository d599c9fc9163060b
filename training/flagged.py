"""Evaluation beside the headline figures: scores without the frame's flare and bulb pixels (preprocess/flare.py),
and which test images are back-lit.

Unflagged scores use the headline (masked, project tonemap) convention over the pixels outside the flare mask:
PSNR from their mean squared error, SSIM as the mean of the SSIM map (training/metrics.py's window) over the valid
window positions centred on them. A test image is back-lit when its light is behind the object as seen from the
camera: the light's direction from the scene centre points away from the camera (angle to the camera's direction
above BACKLIT_ANGLE_DEG), the frames that show light passing through a translucent object.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from lightstage.records.shards import TestImage
from lightstage.tonemap import tonemap
from lightstage.training.metrics import masked, psnr, ssim_map, ssim_valid

BACKLIT_ANGLE_DEG = 90.0


def is_backlit(image: TestImage, centre: np.ndarray | None = None) -> bool:
    """The image's light direction makes more than BACKLIT_ANGLE_DEG with the direction from the scene centre
    (world origin unless given) to the camera."""
    c = np.zeros(3) if centre is None else np.asarray(centre, np.float64)
    to_cam = image.camera.center - c
    to_cam = to_cam / max(float(np.linalg.norm(to_cam)), 1e-12)
    light = np.asarray(image.light_direction, np.float64)
    light = light / max(float(np.linalg.norm(light)), 1e-12)
    return bool(float(light @ to_cam) < np.cos(np.deg2rad(BACKLIT_ANGLE_DEG)))


def unflagged_psnr(pred: np.ndarray, target: np.ndarray, keep: np.ndarray) -> float | None:
    """PSNR of [0, 1] images over the (H, W) pixels where `keep` is set (None when none is)."""
    return psnr(np.asarray(pred)[keep], np.asarray(target)[keep]) if keep.any() else None


def unflagged_ssim(pred: np.ndarray, target: np.ndarray, keep: np.ndarray) -> float | None:
    """Mean SSIM map of [0, 1] RGB images over valid window positions centred where `keep` is set."""
    sel = ssim_valid(keep.shape) & keep
    return float(ssim_map(pred, target)[sel].mean()) if sel.any() else None


def flag_scores(pred: np.ndarray, image: TestImage, exposure: float) -> dict[str, Any]:
    """psnr_unflagged, ssim_unflagged (module docstring), flagged_fraction of the image's pixels, and backlit."""
    h, w = image.target.shape[:2]
    flare = image.flare if image.flare is not None else np.zeros((h, w), bool)
    keep = ~np.asarray(flare, bool)
    p, t = tonemap(pred, exposure), tonemap(masked(image.target, image.mask), exposure)
    return {
        "psnr_unflagged": unflagged_psnr(p, t, keep),
        "ssim_unflagged": unflagged_ssim(p, t, keep),
        "flagged_fraction": float(flare.mean()),
        "backlit": is_backlit(image),
    }
