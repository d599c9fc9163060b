"""Per-frame thumbnails, the per-frame "lit" threshold, and flare/outlier scores.

While a view streams by, each frame leaves a small luminance thumbnail and a saturated-fraction thumbnail
(a few KB). Once the view's mask is known, a frame's flare score is the light it puts outside the dilated
mask beyond twice the view's typical background (per-pixel upper quartile over frames), saturated bulbs counted at the
cutoff, relative to the view's typical foreground energy. Frames scoring above the threshold are rejected.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# Percentile of a frame's thumbnail luminance taken as its dark (background) level.
DARK_PERCENTILE = 5.0
# Flare scores count light beyond TYPICAL_FACTOR x this per-pixel percentile over the view's frames.
TYPICAL_PERCENTILE = 75.0
TYPICAL_FACTOR = 2.0


@dataclass(frozen=True)
class Thumbnail:
    """A frame's luminance and saturated-fraction thumbnails."""

    lum: np.ndarray  # (th, tw) float32
    saturated: np.ndarray  # (th, tw) float32, fraction of saturated processed pixels


def thumbnail(
    lum: np.ndarray, saturated: np.ndarray, factor: int, scratch: np.ndarray | None = None
) -> Thumbnail:
    """Area-average thumbnails (factor x smaller, at least 1x1) of luminance and saturation flags; the last
    rows/columns that do not fill a block are left out (OpenCV's integer-factor path, 5x faster).
    `scratch`: a float32 array of lum's shape for the flags as numbers (a chunk task reuses one)."""
    import cv2

    lum, saturated = _whole_blocks(lum, factor), _whole_blocks(saturated, factor)
    h, w = lum.shape
    size = (max(1, w // factor), max(1, h // factor))
    t_lum = cv2.resize(lum, size, interpolation=cv2.INTER_AREA)
    flags = np.empty(saturated.shape, np.float32) if scratch is None else _whole_blocks(scratch, factor)
    np.copyto(flags, saturated)
    t_sat = cv2.resize(flags, size, interpolation=cv2.INTER_AREA)
    return Thumbnail(t_lum, t_sat)


def _whole_blocks(img: np.ndarray, factor: int) -> np.ndarray:
    """`img` cropped to whole factor x factor blocks (unchanged when a side is shorter than one block)."""
    h, w = img.shape[:2]
    return img[: h - h % factor if h >= factor else h, : w - w % factor if w >= factor else w]


def lit_threshold(thumb: Thumbnail, cutoff: float, ratio: float = 4.0, floor: float = 2.0**-13) -> float:
    """Luminance above which a pixel counts as lit in this frame: `ratio` x the frame's dark level (robust
    to flares and exposure) plus `floor` x the cutoff (0.00054 for the reference stage at the default)."""
    dark = float(np.percentile(thumb.lum, DARK_PERCENTILE))
    return ratio * max(dark, 0.0) + floor * cutoff


def mask_thumbnail(mask: np.ndarray, dilate: int, factor: int) -> np.ndarray:
    """(th, tw) bool: pixels of a `factor` x smaller thumbnail (as `thumbnail`) that touch the mask dilated by
    `dilate` pixels."""
    import cv2

    m = mask.astype(np.uint8)
    if dilate > 0:
        m = cv2.dilate(m, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * dilate + 1, 2 * dilate + 1)))
    m = _whole_blocks(m, factor)  # the area the frame thumbnails cover
    shape = (max(1, m.shape[0] // factor), max(1, m.shape[1] // factor))
    t = cv2.resize(m.astype(np.float32), (shape[1], shape[0]), interpolation=cv2.INTER_AREA)
    return t > 0


def flare_scores(
    lum_thumbs: np.ndarray,
    sat_thumbs: np.ndarray,
    mask: np.ndarray,
    dilate: int,
    cutoff: float,
    factor: int,
) -> np.ndarray:
    """(k,) flare scores of a view's k frames from their (k, th, tw) thumbnails (`factor` x smaller, see
    `thumbnail`) and the view's mask."""
    k, th, tw = lum_thumbs.shape
    if k == 0:
        return np.zeros(0)
    inside = mask_thumbnail(mask, dilate, factor)
    outside = ~inside
    px = _whole_blocks(mask, factor).size / float(th * tw)  # processed pixels per thumbnail pixel
    # the light a frame adds beyond twice the view's upper-quartile background: a lit backdrop varies with the
    # light within that range (it is lit in most frames), a flare far beyond it
    typical = TYPICAL_FACTOR * np.percentile(lum_thumbs, TYPICAL_PERCENTILE, axis=0)
    excess = np.maximum(lum_thumbs - typical[None], 0.0)
    excess = np.maximum(excess, sat_thumbs * cutoff)  # saturated area counts at the cutoff
    outside_energy = (excess[:, outside]).sum(axis=1) * px
    fg = mask_thumbnail(mask, 0, factor) if mask.any() else inside
    fg_energy = float(np.median(lum_thumbs[:, fg].sum(axis=1) * px)) if fg.any() else 0.0
    floor = 1e-3 * cutoff * mask.size  # scale for views with no or a dark foreground
    return outside_energy / max(fg_energy, floor)
