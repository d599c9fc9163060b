"""The 8-bit images SfM runs on: the preprocess well-lit images, or sharper ones built from the raw capture.

SfM accuracy scales with image resolution, and the preprocess outputs are 4x downscaled (192x128 for the
simulator's `small` capture, whose raw frames are 768x512). `sfm_image_factor` picks the largest resolution
`raw / f` (f an integer dividing the raw size, f <= DOWNSCALE) whose long side is within a cap; f = DOWNSCALE means
the preprocess well-lit images are used as they are (no raw reads: the paper's 8192-px frames give 2048 px).
Otherwise each view's image is the mean of a few raw frames (evenly spread lights, the same for every view:
lights are locked to the rig, so the lighting seen by a camera is the same in every group), optionally leaving
out each pixel's brightest frame (a specular highlight comes from one light and moves with the rig, not with the
object), area-downscaled by f, tonemapped with lightstage's one tonemap and one exposure for the capture; its feature mask is the preprocess
mask upsampled (nearest).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

from lightstage.capture.frames import read_exr, write_image
from lightstage.capture.layout import Capture, FrameId, ViewId
from lightstage.errors import LightstageError
from lightstage.tonemap import tonemap_u8
from lightstage.workdir import DOWNSCALE

LUMA = np.array([0.2126, 0.7152, 0.0722], np.float32)


@dataclass(frozen=True)
class SfmImages:
    """Per view the (image PNG, mask PNG) for SfM, and the downscale factor from raw resolution."""

    views: dict[ViewId, tuple[Path, Path]]
    factor: int
    width: int
    height: int
    lights: list[int]  # raw frames averaged per view ([] when the preprocess images are used)
    exposure: float | None
    seconds: float
    skipped: list[str] = field(default_factory=list)  # raw frames that could not be read (left out)


def sfm_image_factor(width: int, height: int, max_side: int) -> int:
    """Smallest integer downscale f <= DOWNSCALE dividing the raw size with max(w, h) / f <= max_side;
    DOWNSCALE (the preprocess images) when `max_side` <= 0 or nothing smaller fits."""
    if max_side <= 0:
        return DOWNSCALE
    for f in range(1, DOWNSCALE + 1):
        if width % f == 0 and height % f == 0 and max(width, height) // f <= max_side:
            return f
    return DOWNSCALE


def spread_lights(indices: list[int], count: int) -> list[int]:
    """`count` light indices evenly spread over the sorted `indices` (all of them when count <= 0 or larger)."""
    indices = sorted(indices)
    if count <= 0 or count >= len(indices):
        return indices
    picks = np.round(np.linspace(0, len(indices) - 1, count)).astype(int)
    return [indices[i] for i in sorted(set(picks.tolist()))]


def _mean_image(
    capture: Capture, view: ViewId, lights: list[int], factor: int, skipped: list[str], trim: bool = False
) -> np.ndarray:
    """Mean of the view's raw frames over `lights` (with `trim`, per pixel and channel without the brightest
    one), area-downscaled by `factor` (float32 RGB). Unreadable frames are left out (and appended to `skipped`);
    a view with none readable is an error."""
    st = capture.stage
    acc = np.zeros((st.height, st.width, 3), np.float32)
    top = np.zeros_like(acc) if trim else None
    used = 0
    for light in lights:
        path = capture.frame_path(FrameId(view.group, view.camera, light))
        try:
            frame = read_exr(path, (st.width, st.height))
        except LightstageError as e:
            skipped.append(str(e))
            continue
        acc += frame
        if top is not None:
            np.maximum(top, frame, out=top)
        used += 1
    if not used:
        raise LightstageError(f"SfM images: no readable raw frame of view {view} ({skipped[-1]})")
    if top is not None and used > 2:
        acc -= top  # leave out each pixel's brightest light: a specular highlight comes from one light
        used -= 1
    acc *= np.float32(capture.info.exposure_scale / used)
    if factor > 1:
        acc = cv2.resize(acc, (st.width // factor, st.height // factor), interpolation=cv2.INTER_AREA)
    return acc


def _load_mask(path: Path, size: tuple[int, int]) -> np.ndarray:
    m = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    if m is None:
        raise LightstageError(f"{path}: cannot read the foreground mask")
    return cv2.resize(np.where(m > 127, 255, 0).astype(np.uint8), size, interpolation=cv2.INTER_NEAREST)


def build_sfm_images(
    capture: Capture,
    views: dict[ViewId, tuple[Path, Path]],
    out_dir: Path,
    max_side: int,
    num_lights: int,
    trim_brightest: bool = False,
    exposure_percentile: float = 99.0,
    progress: bool = False,
) -> SfmImages:
    """Images for SfM at `raw / sfm_image_factor(...)` (see the module doc). `views`: view -> (preprocess
    well-lit PNG, preprocess mask PNG); raw-derived images and upsampled masks are written under `out_dir`."""
    import time

    t0 = time.perf_counter()
    st = capture.stage
    factor = sfm_image_factor(st.width, st.height, max_side)
    w, h = st.width // factor, st.height // factor
    if factor == DOWNSCALE:
        return SfmImages(dict(views), factor, w, h, [], None, time.perf_counter() - t0)
    lights = spread_lights([lt.index for lt in st.lights], num_lights)
    # One exposure for the capture, from one view per camera of the first group (the preprocess rule: a
    # high percentile of the foreground luminance maps to 1), so every image shares one tonemap.
    sample = [v for v in views if v.group == st.groups[0].name] or list(views)[:1]
    levels, cache, skipped = [], {}, []
    for v in sample:
        img = _mean_image(capture, v, lights, factor, skipped, trim_brightest)
        mask = _load_mask(views[v][1], (w, h)) > 0
        if mask.any():
            levels.append(float(np.percentile(img[mask] @ LUMA, exposure_percentile)))
        cache[v] = img
    levels = [x for x in levels if x > 0]
    exposure = 1.0 / float(np.median(levels)) if levels else 1.0
    out: dict[ViewId, tuple[Path, Path]] = {}
    for v in tqdm(sorted(views), desc="sfm images", unit="view", disable=not progress):
        img = cache.pop(v, None)
        if img is None:
            img = _mean_image(capture, v, lights, factor, skipped, trim_brightest)
        d = out_dir / v.group / v.camera
        d.mkdir(parents=True, exist_ok=True)
        write_image(d / "image.png", tonemap_u8(img, exposure))
        cv2.imwrite(str(d / "mask.png"), _load_mask(views[v][1], (w, h)))
        out[v] = (d / "image.png", d / "mask.png")
    (out_dir / "sfm_images.json").write_text(
        json.dumps({"factor": factor, "size": [w, h], "lights": lights, "exposure": exposure})
    )
    return SfmImages(out, factor, w, h, lights, exposure, time.perf_counter() - t0, skipped)
