"""Decode a raw frame and make its exact 4x area-average downscale plus the per-pixel saturation flag.

The raw frame is decoded once (OpenEXR, interleaved RGB). Row bands are converted half -> float32 with
PyTorch (vectorised; numpy's half conversion is ~20x slower) into a reused buffer and averaged with
`cv2.resize(INTER_AREA)`, whose integer-factor path sums each 4x4 block in float32 and scales by 1/16 (a
power of two, so no extra rounding). Saturation is tested on the raw half bits: for non-negative halfs the
int16 view orders like the value, so "any of the 16 source samples >= cutoff" needs no float conversion and
only bands that reach the cutoff pay for the per-block test.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from lightstage.capture.frames import read_exr_header
from lightstage.errors import LightstageError
from lightstage.workdir import DOWNSCALE


def saturation_half(cutoff: float) -> np.float16:
    """The smallest half >= cutoff: a half sample is saturated iff it is >= this value."""
    h = np.float16(cutoff)
    if float(h) < cutoff:
        h = np.nextafter(h, np.float16(np.inf))
    return h


@dataclass(frozen=True)
class Downscaled:
    """A processed frame in memory: (h, w, 3) float32 linear RGB and (h, w) bool saturation flags."""

    rgb: np.ndarray
    saturated: np.ndarray


def decode_raw(path: str | os.PathLike[str], size: tuple[int, int]) -> np.ndarray:
    """Decode a raw frame's RGB as an (H, W, 3) half or float array (possibly a strided view).

    Header problems (not an EXR, truncated, wrong size, missing channels) raise a LightstageError naming
    the file before any pixels are decoded.
    """
    import OpenEXR

    path = Path(path)
    header = read_exr_header(path)
    problem = getattr(header, "chunk_problem", None)
    if problem:
        raise LightstageError(f"{path}: {problem}")
    if (header.width, header.height) != tuple(size):
        raise LightstageError(
            f"{path}: resolution {header.width}x{header.height}, expected {size[0]}x{size[1]}"
        )
    missing = [c for c in "RGB" if c not in header.channels]
    if missing:
        raise LightstageError(f"{path}: missing channel(s) {', '.join(missing)}")
    kinds = {header.channels[c] for c in "RGB"}
    if len(kinds) != 1 or not kinds <= {"half", "float"}:
        raise LightstageError(f"{path}: R, G, B must all be half or all float, got {sorted(kinds)}")
    try:
        f = OpenEXR.File(str(path))
        channels = f.parts[0].channels
        if "RGB" in channels:
            pixels = channels["RGB"].pixels
        elif "RGBA" in channels:
            pixels = channels["RGBA"].pixels[..., :3]
        else:  # unusual channel sets: decode planes separately
            f = OpenEXR.File(str(path), separate_channels=True)
            pixels = np.stack([f.parts[0].channels[c].pixels for c in "RGB"], axis=-1)
    except Exception as e:  # noqa: BLE001 - any decoder failure is a per-frame problem
        text = str(e).strip().splitlines()
        raise LightstageError(
            f"{path}: corrupt EXR pixel data ({text[0][:200] if text else type(e).__name__})"
        ) from None
    if pixels.shape != (size[1], size[0], 3) or pixels.dtype not in (np.float16, np.float32):
        raise LightstageError(
            f"{path}: decoded {pixels.shape} {pixels.dtype}, expected {size[1]}x{size[0]}x3"
        )
    return pixels


def downscale(pixels: np.ndarray, cutoff: float, band_rows: int = 256, factor: int = DOWNSCALE) -> Downscaled:
    """Exact `factor`x area average of (H, W, 3) half/float pixels in float32, and the saturation flags
    (a processed pixel is saturated when any channel of any of its factor^2 sources is >= cutoff)."""
    import cv2
    import torch

    H, W, C = pixels.shape
    if H % factor or W % factor or C != 3:
        raise LightstageError(f"frame {W}x{H}x{C}: size must be a multiple of {factor} with 3 channels")
    band_rows = max(factor, band_rows - band_rows % factor)
    h, w = H // factor, W // factor
    out = np.empty((h, w, 3), np.float32)
    sat = np.zeros((h, w), bool)
    buf = torch.empty((min(band_rows, H), W, 3), dtype=torch.float32)
    buf_np = buf.numpy()
    src = torch.from_numpy(np.asarray(pixels))
    half = pixels.dtype == np.float16
    if half:
        bits_src = torch.from_numpy(np.asarray(pixels).view(np.int16))
        cut_bits = int(saturation_half(cutoff).view(np.int16))
    for y in range(0, H, band_rows):
        n = min(band_rows, H - y)
        buf[:n].copy_(src[y : y + n])
        cv2.resize(
            buf_np[:n],
            (w, n // factor),
            dst=out[y // factor : (y + n) // factor],
            interpolation=cv2.INTER_AREA,
        )
        if half:
            if int(bits_src[y : y + n].max()) >= cut_bits:
                flags = np.asarray(pixels[y : y + n]).view(np.int16) >= cut_bits
                # NaN bit patterns also compare high; such frames are rejected as non-finite anyway
                sat[y // factor : (y + n) // factor] = _block_any(flags.any(axis=-1), factor)
        else:
            band = buf_np[:n]
            if float(band.max()) >= cutoff:
                sat[y // factor : (y + n) // factor] = _block_any((band >= cutoff).any(axis=-1), factor)
    return Downscaled(out, sat)


def _block_any(flags: np.ndarray, factor: int) -> np.ndarray:
    """(n, W) bool -> (n/f, W/f): True where any sample of the f x f block is True."""
    n, W = flags.shape
    return flags.reshape(n // factor, factor, W // factor, factor).any(axis=(1, 3))


def downscale_reference(pixels: np.ndarray, cutoff: float, factor: int = DOWNSCALE) -> Downscaled:
    """Slow float64 reference of `downscale` (tests): box mean and any-saturated per block."""
    x = np.asarray(pixels, np.float64)
    H, W, C = x.shape
    blocks = x.reshape(H // factor, factor, W // factor, factor, C)
    mean = blocks.mean(axis=(1, 3))
    sat = (blocks >= float(saturation_half(cutoff)) if pixels.dtype == np.float16 else blocks >= cutoff).any(
        axis=(1, 3, 4)
    )
    return Downscaled(mean, sat)
