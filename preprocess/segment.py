"""Foreground segmentation of a view from its OLAT statistics (the paper's heuristics), zone map and overlay.

1. Coarse mask: the object changes with the light direction, so a foreground pixel is lit (above the
   frame's dark level) in a sizeable fraction of the unsaturated frames; the background stays dark apart
   from noise, saturated bulbs (excluded per frame) and flares (a few frames), so its lit fraction is small.
2. Clean-up with OpenCV: opening/closing, connected components (keep the large ones near the image centre),
   hole filling.
3. Sub-pixel boundary: a silhouette pixel mixes object and background linearly, so near the coarse boundary
   a pixel is foreground when its mean (unsaturated) luminance is at least halfway between the local
   object level and the local background level (normalised Gaussian averages of the inside and outside).
"""

from __future__ import annotations

import os

import numpy as np

from lightstage.errors import LightstageError
from lightstage.preprocess.config import PreprocessConfig
from lightstage.preprocess.stats import ViewStats
from lightstage.workdir import ZONE_BACKGROUND, ZONE_BAND, ZONE_FOREGROUND


def _disk(radius: int) -> np.ndarray:
    import cv2

    return cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * radius + 1, 2 * radius + 1))


def fill_holes(mask: np.ndarray) -> np.ndarray:
    """Fill background regions not connected to the image border."""
    import cv2

    h, w = mask.shape
    flood = np.pad(mask.astype(np.uint8), 1)
    ff_mask = np.zeros((h + 4, w + 4), np.uint8)
    cv2.floodFill(flood, ff_mask, (0, 0), 1)
    return mask | (flood[1:-1, 1:-1] == 0)


def keep_components(mask: np.ndarray, config: PreprocessConfig) -> np.ndarray:
    """Keep the connected components that are large and central: each is scored by its area discounted by
    the distance of its centroid from the image centre; components scoring at least `min_component_fraction`
    of the best are kept."""
    import cv2

    n, labels, stats, centroids = cv2.connectedComponentsWithStats(mask.astype(np.uint8), connectivity=8)
    if n <= 1:
        return mask.astype(bool)
    h, w = mask.shape
    area = stats[1:, cv2.CC_STAT_AREA].astype(np.float64)
    off = (centroids[1:] - np.array([w / 2.0, h / 2.0])) / (0.5 * np.hypot(w, h))
    score = area / (1.0 + config.centre_weight * np.hypot(off[:, 0], off[:, 1]) * 4.0)
    keep = np.nonzero(score >= config.min_component_fraction * score.max())[0] + 1
    return np.isin(labels, keep)


def _normalised_blur(values: np.ndarray, weights: np.ndarray, sigma: float) -> np.ndarray:
    import cv2

    w = weights.astype(np.float32)
    num = cv2.GaussianBlur(values.astype(np.float32) * w, (0, 0), sigma)
    den = cv2.GaussianBlur(w, (0, 0), sigma)
    return num / np.maximum(den, 1e-6)


def refine_boundary(mask: np.ndarray, level: np.ndarray, radius: int = 1, sigma: float = 1.5) -> np.ndarray:
    """Decide the pixels within `radius` of the mask boundary by linear unmixing of `level` (a quantity
    linear in coverage, e.g. mean luminance): foreground iff level >= (inside + outside) / 2 locally."""
    import cv2

    m8 = mask.astype(np.uint8)
    inner = cv2.erode(m8, _disk(radius)).astype(bool)
    outer = ~cv2.dilate(m8, _disk(radius)).astype(bool)
    if not inner.any() or not outer.any():
        return mask.astype(bool)
    inside = _normalised_blur(level, inner, sigma)
    outside = _normalised_blur(level, outer, sigma)
    band = ~inner & ~outer
    out = mask.astype(bool).copy()
    out[band] = level[band] >= 0.5 * (inside[band] + outside[band])
    return out


def segment(stats: ViewStats, config: PreprocessConfig) -> np.ndarray:
    """(h, w) bool foreground mask from a view's statistics."""
    import cv2

    if stats.count == 0:
        return np.zeros(stats.peak.shape, bool)
    unsat = stats.unsaturated
    mostly_unsat = stats.saturated <= config.max_saturated_fraction * stats.count
    coarse = (stats.lit_fraction() >= config.min_lit_fraction) & mostly_unsat & (unsat > 0)
    m = coarse.astype(np.uint8)
    if config.open_radius:
        m = cv2.morphologyEx(m, cv2.MORPH_OPEN, _disk(config.open_radius))
    if config.close_radius:
        m = cv2.morphologyEx(m, cv2.MORPH_CLOSE, _disk(config.close_radius))
    mask = keep_components(m.astype(bool), config)
    if config.fill_holes:
        mask = fill_holes(mask)
    if mask.any():
        mask = refine_boundary(mask, stats.unsaturated_mean_luminance())
        mask = keep_components(mask, config)
        if config.fill_holes:
            mask = fill_holes(mask)
    return mask


def zone_map(mask: np.ndarray, band_width: int) -> np.ndarray:
    """uint8 zones: ZONE_FOREGROUND inside, ZONE_BAND within `band_width` pixels of the silhouette (both
    sides), ZONE_BACKGROUND elsewhere."""
    import cv2

    zones = np.full(mask.shape, ZONE_BACKGROUND, np.uint8)
    zones[mask] = ZONE_FOREGROUND
    if band_width > 0 and mask.any():
        m8 = mask.astype(np.uint8)
        # distance of every pixel to the other side of the silhouette
        d_out = cv2.distanceTransform(1 - m8, cv2.DIST_L2, 5)  # background pixels: distance to foreground
        d_in = cv2.distanceTransform(m8, cv2.DIST_L2, 5)  # foreground pixels: distance to background
        band = np.where(mask, d_in <= band_width, d_out <= band_width)
        zones[band] = ZONE_BAND
    return zones


def overlay(wellit_u8: np.ndarray, mask: np.ndarray, zones: np.ndarray) -> np.ndarray:
    """RGB preview: the well-lit image, background darkened, band tinted, silhouette outlined in green."""
    import cv2

    img = wellit_u8.astype(np.float32)
    img[~mask] *= 0.35
    band = zones == ZONE_BAND
    img[band] = 0.6 * img[band] + 0.4 * np.array([255, 160, 0], np.float32)
    contours, _ = cv2.findContours(mask.astype(np.uint8), cv2.RETR_LIST, cv2.CHAIN_APPROX_NONE)
    out = np.clip(img, 0, 255).astype(np.uint8)
    cv2.drawContours(out, contours, -1, (0, 255, 0), 1)
    return out


def iou(a: np.ndarray, b: np.ndarray) -> float:
    """Intersection over union of two bool masks (1.0 when both are empty)."""
    union = np.count_nonzero(a | b)
    return float(np.count_nonzero(a & b) / union) if union else 1.0


def read_mask(path: str | os.PathLike[str]) -> np.ndarray:
    """A mask PNG (0/255 or 0/1) as bool (h, w)."""
    import cv2

    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise LightstageError(f"{path}: unreadable mask PNG")
    if img.ndim == 3:
        img = img[..., 0]
    return img > (127 if img.max() > 1 else 0)
