"""Per-frame thumbnails, the per-frame "lit" threshold, flare scores and the per-frame flare and bulb masks.

While a view streams by, each frame leaves a small luminance thumbnail and a saturated-fraction thumbnail
(a few KB). Once the view's mask is known, a frame's flare score is the light it puts outside the dilated
mask beyond twice the view's typical background (per-pixel upper quartile over frames), saturated bulbs counted at the
cutoff, relative to the view's typical foreground energy.

Only a frame whose light is in view can flare: the light's nominal position (stage.yaml) projected through the
view's nominal camera lands inside the frame widened by a margin (`light_pixels`). Every other frame scores 0,
however bright its highlights or its object. A frame with its light in view gets a flare mask (`flare_region`):
the pixels outside the object that the bulb or its flare lights beyond the view's typical background, and a disc
around the light's image as far out as the flare's radial profile stays above the level that matters there (the
background level, or a fraction of the frame's own object level), so object pixels the flare veils are flagged
too. docs/preprocess.md states the rules.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lightstage.cameras import PinholeCamera
from lightstage.ids import FrameId, ViewId
from lightstage.preprocess.config import PreprocessConfig
from lightstage.workdir import WorkDir

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


def flare_scores_in_view(
    lum_thumbs: np.ndarray,
    sat_thumbs: np.ndarray,
    mask: np.ndarray,
    dilate: int,
    cutoff: float,
    factor: int,
    centres: list[tuple[float, float] | None],
) -> np.ndarray:
    """`flare_scores`, 0 for every frame whose light is not in view (`centres[k]` None): bright highlights and
    a bright object are never a flare."""
    in_view = np.array([c is not None for c in centres], bool)
    if not in_view.any():  # most views: nothing to score
        return np.zeros(lum_thumbs.shape[0])
    scores = flare_scores(lum_thumbs, sat_thumbs, mask, dilate, cutoff, factor)
    return np.where(in_view, scores, 0.0)


# ---- where a light is in view ---------------------------------------------------------------------------------
def light_pixels(
    camera: PinholeCamera, positions: np.ndarray, size: tuple[int, int], margin: float
) -> list[tuple[float, float] | None]:
    """Per light (rows of `positions`, world metres), the pixel (u, v) of a processed frame of `size` (w, h)
    where the light projects through the view's `camera` (raw resolution, distortion ignored), or None when it
    is behind the camera or outside the frame widened on every side by `margin` x the frame's diagonal (nominal
    geometry is a few pixels off, and a light just outside the frame still flares)."""
    w, h = size
    scale = w / camera.width
    pad = margin * float(np.hypot(w, h))
    pc = np.asarray(positions, np.float64).reshape(-1, 3) @ camera.R.T + camera.t
    out: list[tuple[float, float] | None] = []
    for x, y, z in pc:
        if z <= 1e-9:
            out.append(None)
            continue
        u = (camera.K[0, 0] * x / z + camera.K[0, 2]) * scale
        v = (camera.K[1, 1] * y / z + camera.K[1, 2]) * scale
        inside = -pad <= u <= w + pad and -pad <= v <= h + pad
        out.append((float(u), float(v)) if inside else None)
    return out


# ---- the per-frame flare and bulb mask -------------------------------------------------------------------------
@dataclass(frozen=True)
class FlareRegion:
    """What a frame's bulb and flare light up: thumbnail blocks outside the object (`blocks`, (th, tw) bool, the
    bulb's and the flare's lit blocks and their neighbours) and a disc of `radius` processed pixels around the
    light's image `centre` (u, v), where the flare veils the object too."""

    centre: tuple[float, float]
    radius: float
    blocks: np.ndarray


def flare_regions(
    lum_thumbs: np.ndarray,
    sat_thumbs: np.ndarray,
    mask: np.ndarray,
    dilate: int,
    factor: int,
    centres: list[tuple[float, float] | None],
    veil: float,
    floor_level: float,
) -> list[FlareRegion | None]:
    """Per frame, its FlareRegion, or None when its light is not in view or lights nothing outside the object.

    Levels come from the view: a block outside the dilated mask is lit by the flare when the frame exceeds twice
    its per-block upper quartile over frames by more than the view's background level (the median upper quartile
    outside the mask, at least `floor_level`), or holds a saturated pixel (a bulb). The veil disc reaches as far
    as the flare's radial profile outside the object (median excess per ring around the bulb, `bulb_centre`, made
    non-increasing outward) exceeds the larger of the background level and `veil` x the frame's median object
    level: glare weaker than that changes an object pixel by less than `veil` of its typical value."""
    k = lum_thumbs.shape[0]
    if all(c is None for c in centres):
        return [None] * k
    th, tw = lum_thumbs.shape[1:]
    outside = ~mask_thumbnail(mask, dilate, factor)
    fg = mask_thumbnail(mask, 0, factor) if mask.any() else np.zeros((th, tw), bool)
    upper = np.percentile(lum_thumbs, TYPICAL_PERCENTILE, axis=0)
    background = float(np.median(upper[outside])) if outside.any() else float(np.median(upper))
    background = max(background, floor_level)
    rows, cols = np.mgrid[0:th, 0:tw]
    out: list[FlareRegion | None] = []
    for i in range(k):
        if centres[i] is None:
            out.append(None)
            continue
        excess = lum_thumbs[i] - TYPICAL_FACTOR * upper
        lit = outside & ((excess > background) | (sat_thumbs[i] > 0))
        if not lit.any():
            out.append(None)
            continue
        u, v = bulb_centre(outside & (sat_thumbs[i] > 0), centres[i], factor)
        ring = np.hypot((cols + 0.5) - u / factor, (rows + 0.5) - v / factor).astype(np.int64)
        object_level = float(np.median(lum_thumbs[i][fg])) if fg.any() else 0.0
        level = max(background, veil * object_level)
        rings = radial_profile(np.maximum(excess, 0.0)[outside], ring[outside])
        above = np.flatnonzero(rings > level)
        radius = float((above[-1] + 1) * factor) if above.size else 0.0
        out.append(FlareRegion((u, v), radius, dilate_blocks(lit)))
    return out


def bulb_centre(saturated: np.ndarray, nominal: tuple[float, float], factor: int) -> tuple[float, float]:
    """The centre (u, v, processed pixels) of the flare: the centroid of the saturated blob outside the object
    (the bulb, (th, tw) blocks) nearest the light's nominal image, else the nominal image itself (the bulb is
    hidden): a stage's nominal geometry may be some pixels off the bulb actually seen."""
    import cv2

    if not saturated.any():
        return nominal
    n, _, _, centroids = cv2.connectedComponentsWithStats(saturated.astype(np.uint8), connectivity=8)
    blobs = (centroids[1:n] + 0.5) * factor  # block centres -> processed pixels
    k = int(np.argmin(np.hypot(blobs[:, 0] - nominal[0], blobs[:, 1] - nominal[1])))
    return float(blobs[k, 0]), float(blobs[k, 1])


def radial_profile(values: np.ndarray, ring: np.ndarray) -> np.ndarray:
    """(max ring + 1,) median of `values` per integer ring, made non-increasing outward (each ring takes the
    largest median at or beyond it; rings without samples, e.g. hidden by the object, inherit from outside)."""
    if values.size == 0:
        return np.zeros(0)
    n = int(ring.max()) + 1
    med = np.zeros(n)
    order = np.argsort(ring, kind="stable")
    r, x = ring[order], values[order]
    starts = np.searchsorted(r, np.arange(n + 1))
    for j in range(n):
        if starts[j + 1] > starts[j]:
            med[j] = float(np.median(x[starts[j] : starts[j + 1]]))
    return np.maximum.accumulate(med[::-1])[::-1]


def dilate_blocks(blocks: np.ndarray) -> np.ndarray:
    """(th, tw) bool grown by one block in every direction (8-neighbours): a bulb or flare edge that only
    partly fills a block lies within it or its neighbour."""
    import cv2

    return cv2.dilate(blocks.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0


def flare_mask(region: FlareRegion, size: tuple[int, int], factor: int) -> np.ndarray:
    """(h, w) bool mask of a processed frame of `size` (w, h): the region's blocks (each `factor` x `factor`
    processed pixels; the last partial rows and columns take their neighbour block's value) and its veil disc."""
    import cv2

    w, h = size
    up = np.repeat(np.repeat(region.blocks, factor, axis=0), factor, axis=1)[:h, :w]
    up = cv2.copyMakeBorder(
        up.astype(np.uint8), 0, h - up.shape[0], 0, w - up.shape[1], cv2.BORDER_REPLICATE
    ).astype(bool)
    if region.radius > 0:
        u, v = region.centre
        yy, xx = np.ogrid[0:h, 0:w]
        up |= (xx + 0.5 - u) ** 2 + (yy + 0.5 - v) ** 2 <= region.radius**2
    return up


def frame_levels(lum_thumbs: np.ndarray, sat_thumbs: np.ndarray) -> np.ndarray:
    """(k,) mean luminance of each frame's thumbnail over its blocks without a saturated pixel (clipped
    highlights move as the object turns; all blocks when every one has one): what the broken-frame test
    (preprocess/broken.py) compares across groups."""
    k = lum_thumbs.shape[0]
    if k == 0:
        return np.zeros(0)
    lum = lum_thumbs.reshape(k, -1).astype(np.float64)
    clear = sat_thumbs.reshape(k, -1) <= 0
    n = clear.sum(axis=1)
    return np.where(n > 0, (lum * clear).sum(axis=1) / np.maximum(n, 1), lum.mean(axis=1))


# ---- a view's flares ------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class ViewFlares:
    """A view's flare outcome: per frame (the view's lights, in order) its score; the level of each frame whose
    light is not in view (light -> level; the broken-frame test leaves the others out: whether the turning object
    hides the bulb changes their level from group to group); the frames the `drop` policy rejects; the flare
    regions the `mask` policy writes (light -> FlareRegion)."""

    scores: np.ndarray
    levels: dict[int, float]
    rejected: list[int]
    regions: dict[int, FlareRegion]


def view_flares(
    lum_thumbs: np.ndarray,
    sat_thumbs: np.ndarray,
    mask: np.ndarray,
    lights: list[int],
    light_pixels_of: dict[int, tuple[float, float] | None],
    config: PreprocessConfig,
    cutoff: float,
) -> ViewFlares:
    """Scores, levels, rejects and flare regions of a view's frames (thumbnails in the order of `lights`) under
    the configured flare_policy; `light_pixels_of`: light -> its image when in view (ViewJob.light_pixels)."""
    centres = [light_pixels_of.get(lt) for lt in lights]
    args = (lum_thumbs, sat_thumbs, mask, config.flare_dilate)
    scores = flare_scores_in_view(*args, cutoff, config.flare_thumb, centres)
    rejected: list[int] = []
    regions: dict[int, FlareRegion] = {}
    if config.flare_policy == "drop":
        rejected = [lt for lt, s in zip(lights, scores, strict=True) if s > config.flare_threshold]
    else:
        found = flare_regions(
            *args, config.flare_thumb, centres, config.flare_veil, config.lit_floor * cutoff
        )
        regions = {lt: r for lt, r in zip(lights, found, strict=True) if r is not None}
    levels = {
        lt: float(x)
        for lt, x, c in zip(lights, frame_levels(lum_thumbs, sat_thumbs), centres, strict=True)
        if c is None
    }
    return ViewFlares(scores, levels, rejected, regions)


def write_flare_masks(
    work: WorkDir, view: ViewId, regions: dict[int, FlareRegion], size: tuple[int, int], factor: int
) -> dict[str, float]:
    """Write each region's flare mask (WorkDir.flare_mask, 0/255 PNG), remove masks of other frames left by an
    earlier run, and return light -> flagged fraction of the frame."""
    from lightstage.frames import write_image

    flagged: dict[str, float] = {}
    keep = set()
    for light, region in sorted(regions.items()):
        path = work.flare_mask(FrameId(view.group, view.camera, light))
        m = flare_mask(region, size, factor)
        write_image(path, m.astype(np.uint8) * 255)
        keep.add(path.name)
        flagged[str(light)] = round(float(m.mean()), 5)
    folder = work.flare_mask(FrameId(view.group, view.camera, 0)).parent
    if folder.is_dir():
        for p in folder.iterdir():
            if p.name not in keep:
                p.unlink(missing_ok=True)  # stale masks and killed writers' temps
    return flagged
