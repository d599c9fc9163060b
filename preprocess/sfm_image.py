"""Each view's image for calibration's SfM: a trimmed mean of a few frames at the largest useful resolution.

SfM accuracy follows image resolution, and processed frames are 4x downscaled (192x128 for the simulator's `small`
capture, whose raw frames are 768x512). `sfm_image_factor` picks the largest resolution raw / f (f an integer
dividing the raw size, f <= DOWNSCALE) whose long side is within a cap: f = DOWNSCALE reads the processed frames
(the paper's 8192-px frames give 2048 px), a smaller f decodes the raw frames in bands at raw / f. The image is the
mean of a few evenly spread lights, the same for every view (lights are locked to the rig, so a camera sees the same
lighting in every group), optionally leaving out each pixel's brightest frame (a specular highlight comes from one
light and moves with the rig, not with the object). Bad and flare-rejected frames are left out.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from lightstage.errors import LightstageError
from lightstage.npyio import load_npy
from lightstage.workdir import DOWNSCALE


def sfm_image_factor(width: int, height: int, max_side: int) -> int:
    """Smallest integer downscale f <= DOWNSCALE dividing the raw size with max(w, h) / f <= max_side;
    DOWNSCALE (the processed frames) when `max_side` <= 0 or nothing smaller fits."""
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


@dataclass(frozen=True)
class SfmSource:
    """Where a view's SfM image comes from: the frames of `lights` (raw paths and processed paths by light)."""

    lights: list[int]
    raw_paths: dict[int, str]
    processed_paths: dict[int, str]
    raw_size: tuple[int, int]  # (width, height)
    factor: int
    cutoff: float
    exposure_scale: float
    band_rows: int = 32
    # light -> .npy a chunk task saved while it had the raw frame decoded (frame_task.decode_frame); a light
    # without one is decoded from its raw frame here
    cached: dict[int, str] = field(default_factory=dict)
    decoder: str = "auto"  # decoder_choice.CHOICES
    read_timeout_s: float = 120.0


def sfm_mean_image(src: SfmSource, trim: bool) -> np.ndarray:
    """(H / f, W / f, 3) float32 linear mean of the source frames (with `trim`, per pixel and channel without the
    brightest one when more than two frames remain). A frame that cannot be read is an error naming it."""
    from lightstage.records.processed import read_processed

    W, H = src.raw_size
    size = (W // src.factor, H // src.factor)
    if not src.lights:
        raise LightstageError("SfM image: no usable frame among the chosen lights")
    acc = np.zeros((size[1], size[0], 3), np.float32)
    top = np.zeros_like(acc) if trim else None
    for light in src.lights:
        if src.factor == DOWNSCALE:
            rgb, _ = read_processed(src.processed_paths[light], size)
        elif light in src.cached and Path(src.cached[light]).is_file():
            rgb = load_npy(src.cached[light])
            if rgb.shape != (size[1], size[0], 3) or rgb.dtype != np.float32:
                raise LightstageError(f"{src.cached[light]}: SfM frame is {rgb.dtype} {rgb.shape}")
        else:
            rgb = _decode_at_factor(src, light)
        acc += rgb
        if top is not None:
            np.maximum(top, rgb, out=top)
    used = len(src.lights)
    if top is not None and used > 2:
        acc -= top  # leave out each pixel's brightest light: a specular highlight comes from one light
        used -= 1
    acc *= np.float32(1.0 / used)
    return acc


def _decode_at_factor(src: SfmSource, light: int) -> np.ndarray:
    """A raw frame at raw / factor, x exposure_scale (what a chunk task saves in `cached`)."""
    from lightstage.exr_header import prefetch_file
    from lightstage.preprocess.decoder_choice import process_chooser
    from lightstage.preprocess.downscale import decode_downscale, decode_raw, downscale

    path = src.raw_paths[light]
    prefetch_file(path, src.read_timeout_s)

    def decode(decoder: str) -> np.ndarray:
        if decoder == "bands":
            return decode_downscale(path, src.raw_size, src.cutoff, src.band_rows, src.factor).rgb
        return downscale(decode_raw(path, src.raw_size), src.cutoff, src.band_rows, src.factor).rgb

    rgb, _ = process_chooser().run(src.decoder, decode)
    rgb *= np.float32(src.exposure_scale)
    return rgb


def upsample_mask(mask: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Processed-resolution bool mask -> uint8 0/255 feature mask of `size` (w, h), nearest neighbour."""
    import cv2

    return cv2.resize(mask.astype(np.uint8) * 255, size, interpolation=cv2.INTER_NEAREST)
