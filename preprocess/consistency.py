"""Cross-group consistency of one camera's masks: stage structure that joined a view's mask is removed.

On a light stage the cameras, the lights and the structure behind the object (cage, cloth) stay where they are
while the turntable rotates the object between groups. So a background pixel of a camera sees the same lights in
every group and its mean over the OLAT stack is the same up to sensor noise, while an object pixel changes as the
object turns. After every view of a camera has its masks, a pixel of a view's inclusive mask whose mean agrees with
the same pixel of at least half of the camera's other groups (within `background_sigmas` of the noise measured on
the camera's own background, where no group sees the object) is fixed to the camera, with the connected pixels that
agree with at least two (the turning object covers a background pixel next to it in some of the other groups).

A rotationally symmetric, evenly coloured object (or part of one) centred on the turntable axis, or an object that
clips the same way in every group, looks fixed too. So each connected part of the fixed pixels is judged from the
data (`structure_parts`): structure, which leaves the mask, when it reaches the frame border, lies mostly outside
the view's own mask, or is nearer the background's brightness than the object's; otherwise it is the object and
stays. When the structure away from the border would take more than `consistency_max_removed` of a view's mask, only
the parts at the border leave. Needs at least 3 groups with the same frames; otherwise the masks stay as they are
(docs/preprocess.md).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from lightstage.preprocess.config import PreprocessConfig
from lightstage.tonemap import luminance

MIN_GROUPS = 3  # a pixel is judged against a majority of the other groups: at least two of them


def noise_fit(level: np.ndarray, diff: np.ndarray, bins: int = 16) -> tuple[float, float] | None:
    """(a, b) of the noise variance of one group's mean image, var = a + b * level (read + shot noise of a mean),
    from pairs of groups at background pixels: `level` their mean, `diff` their difference (variance 2 var).
    Robust per brightness bin (MAD), fitted with relative weights; None when fewer than 2 bins have a spread."""
    if level.size < 20 * bins:
        return None
    edges = np.quantile(level, np.linspace(0, 1, bins + 1))
    idx = np.clip(np.searchsorted(edges, level, side="right") - 1, 0, bins - 1)
    xs, ys = [], []
    for i in range(bins):
        d = diff[idx == i]
        if d.size < 20:
            continue
        s = 1.4826 * float(np.median(np.abs(d - np.median(d))))
        if s > 0:
            xs.append(float(np.median(level[idx == i])))
            ys.append(0.5 * s * s)
    if len(xs) < 2:
        return None
    x, y = np.asarray(xs), np.asarray(ys)
    A = np.stack([np.ones_like(x), np.maximum(x, 0)], axis=1) / y[:, None]
    a, b = np.linalg.lstsq(A, np.ones_like(y), rcond=None)[0]
    if b < 0:  # no shot-noise range measured: a constant
        a, b = float(np.median(y)), 0.0
    elif a < 0:  # no read-noise floor measured: proportional to the level
        b, a = float(np.median(y / np.maximum(x, 1e-12))), 0.0
    return float(a), float(b)


def group_gains(means: np.ndarray, background: np.ndarray) -> np.ndarray:
    """(G,) each group's brightness relative to the median group, measured on background pixels brighter than
    their median (LEDs or exposure drifting between turntable positions); 1 where it cannot be measured."""
    if not background.any():
        return np.ones(len(means), np.float32)
    lum = means[:, background].mean(axis=-1)  # (G, n)
    ref = np.median(lum, axis=0)
    lit = ref > np.median(ref)
    if np.count_nonzero(lit) < 20:
        return np.ones(len(means), np.float32)
    return np.median(lum[:, lit] / ref[lit], axis=1).astype(np.float32)


def match_counts(
    means: np.ndarray, pixels: np.ndarray, noise: list[tuple[float, float]], sigmas: float
) -> np.ndarray:
    """(G, n): for each group and each of the n `pixels` (flat indices), how many other groups' means agree with
    it in every channel within `sigmas` of the noise of a difference (2 x the fitted variance at their level)."""
    g = len(means)
    vals = means.reshape(g, -1, 3)[:, pixels]  # (G, n, 3)
    counts = np.zeros((g, len(pixels)), np.int16)
    a = np.array([n[0] for n in noise], np.float32)
    b = np.array([n[1] for n in noise], np.float32)
    for i in range(g):
        for k in range(i + 1, g):
            level = np.maximum(0.5 * (vals[i] + vals[k]), 0)
            var2 = 2.0 * (a + b * level)
            ok = np.all((vals[i] - vals[k]) ** 2 <= sigmas * sigmas * var2, axis=-1)
            counts[i] += ok
            counts[k] += ok
    return counts


def consistent_masks(
    means: np.ndarray, masks: np.ndarray, config: PreprocessConfig, own: np.ndarray | None = None
) -> tuple[np.ndarray, dict[str, Any]]:
    """(masks, info): each view's mask less the pixels fixed to the camera (module doc). `means` (G, h, w, 3) the
    views' mean images (same frames), `masks` (G, h, w) the masks to clean (the views' inclusive masks), `own`
    what a view keeps where the step cannot run or gives up (default: `masks`). The noise is measured outside
    every mask dilated by `band_width`; what is left is cleaned like a view's mask (components, holes)."""
    own = masks if own is None else own
    import cv2

    from lightstage.preprocess.segment import _disk, fill_holes, keep_components

    sigmas, max_removed, band = config.background_sigmas, config.consistency_max_removed, config.band_width

    g = len(means)
    info: dict[str, Any] = {"groups": g}
    if g < MIN_GROUPS:
        info["skipped"] = f"{g} group(s) with the same frames (needs {MIN_GROUPS})"
        return own, info
    union = np.any(masks, axis=0)
    near = cv2.dilate(union.astype(np.uint8), _disk(max(band, 1))).astype(bool)
    background = ~near
    gains = group_gains(means, background)
    means = means / gains[:, None, None, None]
    # noise of the mean images, per channel, from consecutive groups at pixels no group has in its mask
    noise = []
    for c in range(3):
        lv = np.concatenate(
            [0.5 * (means[i][background, c] + means[(i + 1) % g][background, c]) for i in range(g)]
        )
        df = np.concatenate([means[i][background, c] - means[(i + 1) % g][background, c] for i in range(g)])
        fit = noise_fit(lv, df)
        if fit is None:
            info["skipped"] = "no background to measure the noise on"
            return own, info
        noise.append(fit)
    info["noise"] = [[float(f"{a:.3g}"), float(f"{b:.3g}")] for a, b in noise]
    info["gains"] = [round(float(x), 4) for x in gains]
    pixels = np.flatnonzero(union)
    counts = match_counts(means, pixels, noise, sigmas)
    need = g // 2  # half of the other groups, at least (4 of 8)
    weak = min(2, need)  # ... or, next to such pixels, two others (the object covers it in the rest)
    info["matches_needed"] = [int(need), int(weak)]
    out = masks.copy()
    removed = []
    loglum = np.log2(np.maximum(np.stack([luminance(m) for m in means]), 1e-12))
    for i in range(g):
        strong = _fixed(counts[i] >= need, pixels, masks[i], config.open_radius)
        grow = _fixed(counts[i] >= weak, pixels, masks[i], config.open_radius) | strong
        _, labels = cv2.connectedComponents(grow.astype(np.uint8), connectivity=8)
        seeded = np.unique(labels[strong])
        fixed = np.isin(labels, seeded[seeded > 0])
        total = int(np.count_nonzero(masks[i]))
        if not fixed.any():
            removed.append(0)
            continue
        border, structure = structure_parts(fixed, own[i], loglum[i], background)
        n = int(np.count_nonzero(structure & ~border))
        if n > max_removed * total:  # the object itself looks fixed to the camera: only what leaves the frame
            structure = border
            removed_part = -n
        else:
            removed_part = None
        if not structure.any():
            out[i] = own[i]
            removed.append(removed_part if removed_part is not None else 0)
            continue
        m = keep_components(masks[i] & ~structure, config)
        if config.fill_holes:
            m = fill_holes(m)
        out[i] = m
        removed.append(removed_part if removed_part is not None else int(np.count_nonzero(masks[i] & ~m)))
    info["removed"] = removed
    return out, info


def structure_parts(
    fixed: np.ndarray, own: np.ndarray, loglum: np.ndarray, background: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """(border, structure) of a view's fixed pixels (both (h, w) bool): each connected part of `fixed` is stage
    structure when it reaches the frame border (an object is framed inside the image: a lit floor or a strut
    leaving the frame is not), when it is mostly outside the view's own mask (what the inclusive mask's mean
    layer let in), or when its typical brightness (median log2 luminance of the mean image `loglum`) is nearer
    the background's than the object's (struts and cloth behind the object, 2-3x the cloth, against an object
    several stops brighter). What is left is the object itself looking fixed: a rotationally symmetric, evenly
    coloured object (or part) on the turntable axis, or an overexposed object clipped in every group."""
    import cv2

    n, labels = cv2.connectedComponents(fixed.astype(np.uint8), connectivity=8)
    if n <= 1:
        empty = np.zeros(fixed.shape, bool)
        return empty, empty
    edge = np.zeros(fixed.shape, bool)
    edge[[0, -1], :] = edge[:, [0, -1]] = True
    idx = np.arange(1, n)
    touches = np.isin(idx, np.unique(labels[edge & fixed]))
    from scipy import ndimage

    inside = np.asarray(ndimage.mean(own.astype(np.float32), labels, idx)) >= 0.5
    obj_px = own & ~fixed
    bg = float(np.median(loglum[background])) if background.any() else -np.inf
    obj = float(np.median(loglum[obj_px if obj_px.any() else own])) if own.any() else np.inf
    level = np.asarray(ndimage.median(loglum, labels, idx))
    dim = level < bg + 0.5 * (obj - bg)
    kinds = np.zeros(n, np.int8)  # 0: object, 1: structure, 2: structure at the border
    kinds[1:][~inside | dim] = 1
    kinds[1:][touches] = 2
    return kinds[labels] == 2, kinds[labels] >= 1


def _fixed(agree: np.ndarray, pixels: np.ndarray, mask: np.ndarray, radius: int) -> np.ndarray:
    """(h, w) bool: the masked pixels among `pixels` (flat indices) where `agree`, less single pixels and thin
    lines that agree by chance (dark or plain parts of the object: an opening of `radius`)."""
    import cv2

    from lightstage.preprocess.segment import _disk

    out = np.zeros(mask.shape, bool)
    out.flat[pixels] = agree
    out &= mask
    if radius:
        out = cv2.morphologyEx(out.astype(np.uint8), cv2.MORPH_OPEN, _disk(radius)) > 0
    return out
