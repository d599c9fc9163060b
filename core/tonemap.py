"""The tonemap used for every preview PNG, the 8-bit calibration images and evaluation metrics.

Linear HDR is multiplied by `exposure`, clipped to [0, 1] and encoded with the sRGB transfer curve.
The exposure for a capture is chosen once (see `auto_exposure`) so previews and metrics agree.

`paper_tonemap` is the convention of the paper's evaluation code (sRGB of log(1 + hdr), no exposure), used
only to report metrics that can be set beside the paper's tables.
"""

from __future__ import annotations

import numpy as np

# Rec. 709 luminance weights of linear RGB.
LUMA = (0.2126, 0.7152, 0.0722)
_LUMA_MATRIX = np.array([LUMA], np.float32)


def luminance(rgb: np.ndarray) -> np.ndarray:
    """(h, w, 3) float32 linear RGB -> (h, w) float32 luminance (OpenCV channel transform, vectorised)."""
    import cv2

    return cv2.transform(np.ascontiguousarray(rgb, np.float32), _LUMA_MATRIX)


def srgb_encode(linear: np.ndarray) -> np.ndarray:
    """sRGB OETF of linear values in [0, 1] (IEC 61966-2-1)."""
    x = np.clip(linear, 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1.0 / 2.4) - 0.055)


def tonemap(hdr: np.ndarray, exposure: float = 1.0) -> np.ndarray:
    """Linear HDR -> display-referred float in [0, 1]: sRGB(clip(exposure * hdr))."""
    return srgb_encode(np.asarray(hdr, dtype=np.float32) * np.float32(exposure)).astype(np.float32)


def paper_tonemap(hdr: np.ndarray) -> np.ndarray:
    """Linear HDR -> [0, 1] as the paper's evaluation code scores images: sRGB(clip(log(1 + hdr), 0, 1))."""
    x = np.log1p(np.maximum(np.asarray(hdr, dtype=np.float32), np.float32(0.0)))
    return srgb_encode(x).astype(np.float32)


def tonemap_u8(hdr: np.ndarray, exposure: float = 1.0) -> np.ndarray:
    """`tonemap` quantised to uint8 (for PNG previews and SfM images)."""
    return np.round(tonemap(hdr, exposure) * 255.0).astype(np.uint8)


def auto_exposure(hdr: np.ndarray, percentile: float = 99.0, mask: np.ndarray | None = None) -> float:
    """Exposure that maps the given percentile of the (masked) luminance to 1.0."""
    lum = np.asarray(hdr, dtype=np.float32).mean(axis=-1)
    values = lum[mask] if mask is not None else lum.ravel()
    values = values[np.isfinite(values)]
    level = float(np.percentile(values, percentile)) if values.size else 0.0
    return 1.0 / level if level > 0 else 1.0
