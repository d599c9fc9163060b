"""Foreground segmentation of a view from its OLAT statistics (the paper's heuristics), sanity flags, zone map
and overlay.

The default ("adaptive") sets every threshold from the view's own statistics (docs/preprocess.md):
1. Per pixel, its lit levels: the brightness (stops below the cutoff) that 10%, 25% and 50% of its
   unsaturated frames exceed, read from the brightness ladder (preprocess/stats.py). A quantile over the OLAT
   stack ignores the few frames with a flare or a shadow, and saturated frames (bulbs) are left out; each
   quantile is compared with the background's own distribution of that quantile, and a pixel that stands out
   in any of them is foreground (the shadow side of an object stands out in its brightest frames only).
2. The background's level and spread are measured where the object is not: first from a ring along the frame
   border, carried smoothly inwards (a lit floor along one border and a dark cloth along the others make the ring
   two-valued), then (twice) everywhere outside the dilated mask, smoothed into a local background map (the
   background is lit unevenly). The object's level is the median of what stands clearly above it.
3. A pixel is foreground when its lit level exceeds the local background by `background_sigmas` local
   spreads and by `contrast_fraction` of the way (in stops) to the object level, and is mostly unsaturated.
4. Clean-up with OpenCV: opening/closing, connected components (keep the large ones near the image centre),
   hole filling.
5. Sub-pixel boundary: a silhouette pixel mixes object and background linearly, so near the coarse boundary a
   pixel is foreground when its mean (unsaturated) luminance is at least halfway between the object level
   just inside the rim (a ring 1-2 pixels in, not the brighter interior: the rim is darkened by lights near the
   view axis) and the local background level outside (the mean over every frame: saturated frames included).
6. Colour near the silhouette (`colour_refine`), repeated until it adds nothing.
`segment_masks` also gives an inclusive mask that takes the mean luminance over the stack as one more lit level
(dark parts lit well in a frame or two); the camera's cross-group step (consistency.py) starts from it.
The old rule ("lit_fraction": lit above a per-frame dark level in a fixed fraction of the frames) is kept as
an option. `mask_flags` says when a mask looks wrong (touching most of the border, implausible size): the stage
refuses such a view unless its mask is supplied or accepted (report.add_implausible).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from lightstage.preprocess.config import PreprocessConfig
from lightstage.preprocess.stats import LADDER_STOPS, ViewStats
from lightstage.tonemap import luminance
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


# rounds of colour growth (`colour_band` pixels each) at most; on the simulator's captures it stops after <= 6
COLOUR_ROUNDS = 16


def _normalised_blur(
    values: np.ndarray, weights: np.ndarray, sigma: float, den: np.ndarray | None = None
) -> np.ndarray:
    """Gaussian-weighted local mean of `values` under `weights`; `den` (= _weight_blur(weights, sigma)) may be
    passed when several values share the weights."""
    w = weights.astype(np.float32)
    num = gaussian_blur(values.astype(np.float32) * w, sigma)
    if den is None:
        den = _weight_blur(w, sigma)
    return num / den


def _weight_blur(weights: np.ndarray, sigma: float) -> np.ndarray:
    """The denominator of _normalised_blur: the blurred weights, floored at 1e-6."""
    return np.maximum(gaussian_blur(weights.astype(np.float32), sigma), 1e-6)


# a wide blur runs on an area-downsampled copy with at least this many pixels per sigma, at least MIN_BLUR_SIDE
# pixels on its short side, and at most 8x smaller: a Gaussian of 3 pixels or more is smooth on that grid
BLUR_PIXELS_PER_SIGMA = 3.0
MIN_BLUR_SIDE = 64


def blur_factor(sigma: float, shape: tuple[int, ...] = (1 << 30, 1 << 30)) -> int:
    """The downsampling factor `gaussian_blur` uses for `sigma` on an image of `shape` (1: full resolution)."""
    return int(max(1, min(8, sigma // BLUR_PIXELS_PER_SIGMA, min(shape[:2]) // MIN_BLUR_SIDE)))


def gaussian_blur(img: np.ndarray, sigma: float) -> np.ndarray:
    """cv2.GaussianBlur of a float32 image; a wide one (the background map's ~250 px at 2048x1366) on a copy
    area-downsampled by `blur_factor` and resized back (bilinear): the result is as smooth, and the cost drops
    from ~1 CPU-s per blur to a few ms."""
    import cv2

    f = blur_factor(sigma, img.shape)
    if f == 1:
        return cv2.GaussianBlur(img, (0, 0), sigma)
    h, w = img.shape[:2]
    small = cv2.resize(img, (-(-w // f), -(-h // f)), interpolation=cv2.INTER_AREA)
    small = cv2.GaussianBlur(small, (0, 0), sigma / f)
    return cv2.resize(small, (w, h), interpolation=cv2.INTER_LINEAR)


def refine_boundary(
    mask: np.ndarray, level: np.ndarray, radius: int = 1, sigma: float = 1.5, rim: int = 0
) -> np.ndarray:
    """Decide the pixels within `radius` of the mask boundary by linear unmixing of `level` (a quantity
    linear in coverage, e.g. mean luminance): foreground iff level >= (inside + outside) / 2 locally.
    `rim` > 0: the inside level comes from the ring of that width just inside the band (the rim), not the
    whole interior."""
    import cv2

    m8 = mask.astype(np.uint8)
    inner = cv2.erode(m8, _disk(radius)).astype(bool)
    outer = ~cv2.dilate(m8, _disk(radius)).astype(bool)
    if not inner.any() or not outer.any():
        return mask.astype(bool)
    source = inner
    if rim > 0:
        ring = inner & ~cv2.erode(m8, _disk(radius + rim)).astype(bool)
        source = ring if ring.any() else inner
    inside = _normalised_blur(level, source, sigma)
    outside = _normalised_blur(level, outer, sigma)
    band = ~inner & ~outer
    out = mask.astype(bool).copy()
    out[band] = level[band] >= 0.5 * (inside[band] + outside[band])
    return out


def border_ring(shape: tuple[int, int], fraction: float) -> np.ndarray:
    """(h, w) bool ring along the frame border, `fraction` of the short side wide (at least 2 pixels)."""
    h, w = shape
    b = max(2, int(round(fraction * min(h, w))))
    ring = np.ones(shape, bool)
    ring[b : h - b, b : w - b] = False
    return ring


def _robust(values: np.ndarray) -> tuple[float, float]:
    """(median, 1.4826 x median absolute deviation) of a 1-D array."""
    med = float(np.median(values))
    return med, 1.4826 * float(np.median(np.abs(values - med)))


def segment(stats: ViewStats, config: PreprocessConfig, cutoff: float = 1.0) -> np.ndarray:
    """(h, w) bool foreground mask from a view's statistics."""
    return segment_view(stats, config, cutoff)[0]


def segment_view(
    stats: ViewStats, config: PreprocessConfig, cutoff: float = 1.0
) -> tuple[np.ndarray, dict[str, Any]]:
    """(mask, info): the (h, w) bool foreground mask and what the thresholds were measured as (stops below the
    cutoff: background level and spread in the border ring, object level, threshold at the border)."""
    mask, _, info = segment_masks(stats, config, cutoff)
    return mask, info


def segment_masks(
    stats: ViewStats, config: PreprocessConfig, cutoff: float = 1.0
) -> tuple[np.ndarray, np.ndarray, dict[str, Any]]:
    """(mask, inclusive, info): the view's own mask, and a superset that also takes the mean luminance over the
    stack as a lit level (dark parts lit well in a frame or two; it lets more stage structure in too, which the
    camera's cross-group step, consistency.py, removes: it starts from this one)."""
    if stats.count == 0:
        empty = np.zeros(stats.peak.shape, bool)
        return empty, empty, {}
    if config.segmentation == "lit_fraction" or len(stats.ladder) == 0:
        mask = _segment_lit_fraction(stats, config)
        return mask, mask, {"method": "lit_fraction"}
    return _segment_adaptive(stats, config, cutoff)


def _cleanup(coarse: np.ndarray, stats: ViewStats, config: PreprocessConfig, rim: int) -> np.ndarray:
    """Morphology, components, holes, sub-pixel boundary (steps 4-5 of the module doc)."""
    import cv2

    m = coarse.astype(np.uint8)
    if config.open_radius:
        m = cv2.morphologyEx(m, cv2.MORPH_OPEN, _disk(config.open_radius))
    if config.close_radius:
        m = cv2.morphologyEx(m, cv2.MORPH_CLOSE, _disk(config.close_radius))
    mask = keep_components(m.astype(bool), config)
    if config.fill_holes:
        mask = fill_holes(mask)
    if mask.any():
        mask = refine_boundary(mask, stats.mean_luminance(), rim=rim)
        mask = keep_components(mask, config)
        if config.fill_holes:
            mask = fill_holes(mask)
    return mask


def colour_refine(
    mask: np.ndarray, stats: ViewStats, config: PreprocessConfig, rounds: int = 1
) -> np.ndarray:
    """Add the pixels within `colour_band` of the silhouette whose colour (chromaticity of the mean image over the
    whole stack, which does not depend on brightness) is clearly not the local background's and nearer the
    local object's; next to the silhouette only those no brighter than the local background (a partly covered
    pixel takes the bright object's colour), farther out any: dark-albedo parts, shadowed rims and dark notches
    are as dark as a lit backdrop but keep their colour. Repeated up to `rounds` times while it adds pixels.
    Inactive where the object and the backdrop have the same colour (their chromaticities differ by less than
    `background_sigmas` background spreads), and for pixels below the noise floor of the background."""
    import cv2

    if config.colour_band <= 0 or not mask.any() or mask.all():
        return mask
    rgb = np.maximum(stats.mean.astype(np.float32), 0)
    lum = np.maximum(luminance(rgb), 1e-12)
    chroma = np.log(np.maximum(rgb, 1e-12) / lum[..., None])[..., [0, 2]]  # log r/Y, log b/Y
    sigma = 2.0 * max(config.colour_band, 1)
    m8 = mask.astype(np.uint8)
    # measured once, on the mask as it came: the background's noise floor and chromaticity spread
    away0 = ~cv2.dilate(m8, _disk(config.colour_band + 2)).astype(bool)
    if not away0.any():
        return mask
    # reliable colour: brighter than the background's noise (its lowest decile of mean luminance, twice)
    reliable = lum > 2.0 * float(np.percentile(lum[away0], 10))
    w0 = away0 & reliable
    if not w0.any():
        return mask
    c_bg0 = np.stack([_normalised_blur(chroma[..., k], w0, 4 * sigma) for k in range(2)], axis=-1)
    spread = 1.4826 * float(np.median(np.linalg.norm(chroma[w0] - c_bg0[w0], axis=-1)))
    if not spread > 0:
        return mask
    limit = config.background_sigmas * spread
    # a pixel partly covered by the bright object lies within 1 pixel of the silhouette decided by brightness
    beside = cv2.dilate(m8, _disk(1)).astype(bool) & ~mask
    out = mask.copy()
    for _ in range(max(1, rounds)):
        o8 = out.astype(np.uint8)
        inner = cv2.erode(o8, _disk(2)).astype(bool)
        away = ~cv2.dilate(o8, _disk(config.colour_band + 2)).astype(bool)
        near = cv2.dilate(o8, _disk(config.colour_band)).astype(bool) & ~out & reliable
        w_in, w_out = inner & reliable, away & reliable
        if not near.any() or not w_in.any() or not w_out.any():
            break
        den_in, den_out = _weight_blur(w_in, sigma), _weight_blur(w_out, 4 * sigma)
        idx = np.nonzero(near)
        c = chroma[idx]
        c_obj = np.stack(
            [_normalised_blur(chroma[..., k], w_in, sigma, den_in)[idx] for k in range(2)], axis=-1
        )
        c_bg = np.stack(
            [_normalised_blur(chroma[..., k], w_out, 4 * sigma, den_out)[idx] for k in range(2)], axis=-1
        )
        dev = np.linalg.norm(c - c_bg, axis=-1)
        ok = (np.linalg.norm(c_obj - c_bg, axis=-1) > limit) & (dev > limit)
        ok &= np.linalg.norm(c - c_obj, axis=-1) < dev
        lum_bg = _normalised_blur(lum, w_out, 4 * sigma, den_out)[idx]
        ok &= (lum[idx] < 1.5 * lum_bg) | ~beside[idx]
        if not ok.any():
            break
        grown = out.copy()
        grown[idx[0][ok], idx[1][ok]] = True
        # keep only additions connected to the mask
        _, labels = cv2.connectedComponents(grown.astype(np.uint8), connectivity=8)
        keep = np.unique(labels[out])
        grown = np.isin(labels, keep[keep > 0])
        if np.array_equal(grown, out):
            break
        out = grown
    return out


def _segment_adaptive(
    stats: ViewStats, config: PreprocessConfig, cutoff: float
) -> tuple[np.ndarray, np.ndarray, dict[str, Any]]:
    import cv2

    shape = stats.peak.shape
    # a pixel that clips in most frames is an overexposed part of the object (its saturated frames count as
    # brighter than every level); a bulb clips in its own light's frame only. A user may still bound it.
    mostly_unsat = stats.saturated <= config.max_saturated_fraction * stats.count
    ring = border_ring(shape, config.border_width)
    floor = 0.25  # stops: the ladder's resolution (one level per stop, interpolated)
    sigma = config.background_blur * float(np.hypot(*shape))
    ring_sigma = 0.5 * min(shape)  # wide enough to reach the frame's centre from its border
    ring_den = _weight_blur(ring, ring_sigma)
    # per quantile: lit level (stops re the cutoff, higher = brighter), background map, spread map, object level
    layers = []
    info: dict[str, Any] = {"method": "adaptive", "quantiles": {}}
    # a quantile reaches at least `min_quantile_frames` frames: flares and visible bulbs are in a few frames only
    qs = sorted({max(q, config.min_quantile_frames / max(stats.count, 1)) for q in config.quantiles()})
    # the quantile layers, and the mean unsaturated luminance over the whole stack: a dark or shadowed part of the
    # object lit well in one or two frames only stands out in the mean, not in the quantiles
    for q in [*qs, "mean"]:
        if q == "mean":
            # floored where the ladder ends: darks quantised to 0 must not make a background of -inf stops
            lowest = 2.0 ** -(LADDER_STOPS[-1] + 1)
            level = np.log2(np.maximum(stats.unsaturated_mean_luminance() / cutoff, lowest)).astype(
                np.float32
            )
        else:
            level = stats.brightness_quantile(min(q, 0.9))
        b0, _ = _robust(level[ring])
        # the first background map: the ring's levels carried smoothly inwards (a lit floor along one border
        # and a dark cloth along the others make the ring two-valued: one level for the frame would be either
        # above the floor or far below the object), its spread measured on the ring around that map
        back = _normalised_blur(level, ring, ring_sigma, ring_den)
        s0 = max(_robust(level[ring] - back[ring])[1], floor)
        strong = ~ring & (level > back + max(config.background_sigmas * s0, 2.0 * config.min_contrast_stops))
        if not strong.any():
            continue
        obj = float(np.median(level[strong]))
        # the mean layer takes part in the view's own mask when configured, else only in the inclusive one
        own = q != "mean" or config.mean_layer()
        layers.append([level, back, np.full(shape, s0, np.float32), obj, own])
        info["quantiles"][str(q)] = {
            "background_stops": round(-b0, 3),
            "background_spread_stops": round(s0, 3),
            "object_stops": round(-obj, 3),
        }
    if not layers:
        return np.zeros(shape, bool), np.zeros(shape, bool), info
    mask = inclusive = np.zeros(shape, bool)
    for it in range(3):
        score = np.full(shape, -np.inf, np.float32)
        score_all = np.full(shape, -np.inf, np.float32)
        for level, back, spread, obj, own in layers:
            contrast = np.maximum(
                np.maximum(config.background_sigmas * spread, config.contrast_fraction * (obj - back)),
                config.min_contrast_stops,
            )
            np.maximum(score_all, (level - back) / contrast, out=score_all)
            if own:
                np.maximum(score, (level - back) / contrast, out=score)
        mask = _cleanup((score > 1.0) & mostly_unsat, stats, config, rim=2)
        if it == 2 or not mask.any():
            mask = _colour_grow(mask, stats, config)
            inclusive = mask
            if not np.array_equal(score_all, score):
                inclusive = _colour_grow(
                    _cleanup((score_all > 1.0) & mostly_unsat, stats, config, rim=2),
                    stats,
                    config,
                )
                inclusive |= mask
            break
        # the background where the object is not: outside the dilated mask (the border ring counts double)
        away = ~cv2.dilate(mask.astype(np.uint8), _disk(max(3, config.band_width))).astype(bool)
        if np.count_nonzero(away) < 0.05 * mask.size:
            inclusive = mask
            break
        weight = away.astype(np.float32) * (1.0 + ring)
        den = _weight_blur(weight, sigma)  # shared by every layer's two blurs
        for layer in layers:
            level = layer[0]
            layer[1] = _normalised_blur(level, weight, sigma, den)
            layer[2] = np.maximum(
                1.2533 * _normalised_blur(np.abs(level - layer[1]), weight, sigma, den), floor
            )
    return mask, inclusive, info


def _colour_grow(mask: np.ndarray, stats: ViewStats, config: PreprocessConfig) -> np.ndarray:
    """colour_refine until it adds nothing (at most COLOUR_ROUNDS rounds), then holes filled."""
    mask = colour_refine(mask, stats, config, COLOUR_ROUNDS)
    return fill_holes(mask) if config.fill_holes else mask


def _segment_lit_fraction(stats: ViewStats, config: PreprocessConfig) -> np.ndarray:
    """The old rule: lit (above each frame's dark level + lit_floor x cutoff) in min_lit_fraction of frames."""
    unsat = stats.unsaturated
    mostly_unsat = stats.saturated <= config.max_saturated_fraction * stats.count
    coarse = (stats.lit_fraction() >= config.min_lit_fraction) & mostly_unsat & (unsat > 0)
    return _cleanup(coarse, stats, config, rim=0)


def border_fraction(mask: np.ndarray) -> float:
    """Fraction of the frame's outermost pixels (its perimeter) that are foreground."""
    edge = np.concatenate([mask[0], mask[-1], mask[1:-1, 0], mask[1:-1, -1]])
    return float(edge.mean()) if edge.size else 0.0


def mask_flags(mask: np.ndarray, config: PreprocessConfig) -> list[str]:
    """Why a view's mask looks wrong on its own (empty: plausible): touching most of the border, or a
    foreground fraction outside [flag_min_fraction, flag_max_fraction]."""
    flags = []
    touch = border_fraction(mask)
    if touch > config.flag_border_fraction:
        flags.append(f"mask touches {touch:.0%} of the frame border")
    fg = float(mask.mean())
    if fg > config.flag_max_fraction:
        flags.append(f"foreground covers {fg:.0%} of the frame")
    elif fg < config.flag_min_fraction:
        flags.append(f"foreground covers only {fg:.2%} of the frame")
    return flags


def group_flags(fractions: dict[str, float], ratio: float) -> dict[str, str]:
    """Views (name -> foreground fraction, the views of one group) whose foreground fraction differs from the
    median of the others by more than `ratio` times either way: name -> reason."""
    out: dict[str, str] = {}
    if len(fractions) < 3 or ratio <= 1:
        return out
    for name, f in fractions.items():
        others = [v for k, v in fractions.items() if k != name]
        med = float(np.median(others))
        if med <= 0 and f <= 0:
            continue
        r = (f + 1e-6) / (med + 1e-6)
        if r > ratio or r < 1.0 / ratio:
            out[name] = f"foreground fraction {f:.1%} vs {med:.1%} (median of the other views of its group)"
    return out


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


def overlay(
    wellit_u8: np.ndarray, mask: np.ndarray, zones: np.ndarray, flags: list[str] | None = None
) -> np.ndarray:
    """RGB preview: the well-lit image, background darkened, band tinted, silhouette outlined in green; a
    flagged view gets a red frame and the word FLAGGED (and so does its tile in the demo's masks.png)."""
    import cv2

    img = wellit_u8.astype(np.float32)
    img[~mask] *= 0.35
    band = zones == ZONE_BAND
    img[band] = 0.6 * img[band] + 0.4 * np.array([255, 160, 0], np.float32)
    contours, _ = cv2.findContours(mask.astype(np.uint8), cv2.RETR_LIST, cv2.CHAIN_APPROX_NONE)
    out = np.clip(img, 0, 255).astype(np.uint8)
    cv2.drawContours(out, contours, -1, (0, 255, 0), 1)
    if flags:
        h, w = out.shape[:2]
        t = max(2, min(h, w) // 40)
        cv2.rectangle(out, (0, 0), (w - 1, h - 1), (255, 0, 0), t)
        scale = max(0.3, min(h, w) / 400)
        cv2.putText(
            out, "FLAGGED", (2 * t, 2 * t + int(20 * scale)), cv2.FONT_HERSHEY_SIMPLEX, scale, (255, 0, 0), 1
        )
    return out


def iou(a: np.ndarray, b: np.ndarray) -> float:
    """Intersection over union of two bool masks (1.0 when both are empty)."""
    union = np.count_nonzero(a | b)
    return float(np.count_nonzero(a & b) / union) if union else 1.0
