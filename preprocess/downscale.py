"""Decode a raw frame and make its exact 4x area-average downscale plus the per-pixel saturation flag.

Two decoders give identical results (`DECODERS`, config `decoder`): `openexr` decodes the whole frame with
OpenEXR (`decode_raw`) and then downscales it in row bands (`downscale`); `bands` decodes row bands with
OpenImageIO's scanline reads (`decode_downscale_factors`), so the full frame is never in memory. Which one is
cheaper depends on the machine (docs/benchmarks.md), so the default `auto` measures both in each worker
(`decoder_choice.py`). Half row bands at the processed factor go through
numba kernels (`area_kernel.py`); other bands are converted to float32 with PyTorch (numpy's half conversion
is ~20x slower) into a reused buffer and averaged with `cv2.resize(INTER_AREA)`, whose integer-factor path
sums each 4x4 block in float32 and scales by 1/16 (a power of two, so no extra rounding): the kernels
reproduce its order, so both give the same bits. Saturation is tested on the raw half bits: for non-negative
halfs the int16 view orders like the value, so "any of the 16 source samples >= cutoff" needs no float
conversion and only bands that reach the cutoff pay for the per-block test.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from lightstage.errors import LightstageError
from lightstage.exr_header import check_exr_header, read_exr_header
from lightstage.frames import oiio_error, set_exr_limits
from lightstage.preprocess import area_kernel
from lightstage.workdir import DOWNSCALE


def saturation_half(cutoff: float) -> np.float16:
    """The smallest half >= cutoff: a half sample is saturated iff it is >= this value."""
    h = np.float16(cutoff)
    if float(h) < cutoff:
        h = np.nextafter(h, np.float16(np.inf))
    return h


DECODERS = ("openexr", "bands")


@dataclass(frozen=True)
class Downscaled:
    """A processed frame in memory: (h, w, 3) float32 linear RGB and (h, w) bool saturation flags, with the
    counts of the source's NaN/Inf and negative samples (`lightstage.frames.pixel_verdict` judges them)."""

    rgb: np.ndarray
    saturated: np.ndarray
    non_finite: int = 0
    negative: int = 0


def _check_raw_header(path: Path, size: tuple[int, int]) -> str:
    """Refuse a raw frame whose header is not a complete RGB half/float EXR of `size` (the checks `read_exr`
    makes: truncation, size, decode bytes, channels); return the RGB sample type ('half' or 'float')."""
    header = read_exr_header(path)
    check_exr_header(header, size, "RGB")
    return header.channels["R"]


def decode_raw(path: str | os.PathLike[str], size: tuple[int, int]) -> np.ndarray:
    """Decode a raw frame's RGB as an (H, W, 3) half or float array (possibly a strided view).

    Header problems (not an EXR, truncated, wrong size, missing channels) raise a LightstageError naming
    the file before any pixels are decoded.
    """
    import OpenEXR

    path = Path(path)
    _check_raw_header(path, size)
    set_exr_limits()
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


class BandDownscaler:
    """Exact `factor`x area average of a frame fed as row bands (multiples of `factor` rows, top to bottom),
    plus the saturation flags; the float32 band buffer is reused, so a frame never exists in float32.
    `out`: (rgb, saturated) arrays to fill instead of new ones (a chunk task reuses one pair for its frames:
    fresh memory costs page faults, docs/benchmarks.md)."""

    def __init__(
        self,
        size: tuple[int, int],
        cutoff: float,
        band_rows: int,
        factor: int = DOWNSCALE,
        out: tuple[np.ndarray, np.ndarray] | None = None,
    ) -> None:
        W, H = size
        if H % factor or W % factor:
            raise LightstageError(f"frame {W}x{H}: size must be a multiple of {factor}")
        self.factor, self.size, self.cutoff = factor, (W, H), cutoff
        shape = (H // factor, W // factor)
        if out is None:
            out = (np.empty((*shape, 3), np.float32), np.empty(shape, bool))
        self.rgb, self.saturated = out
        if not (
            self.rgb.shape == (*shape, 3)
            and self.rgb.dtype == np.float32
            and self.saturated.shape == shape
            and self.saturated.dtype == bool
            and self.rgb.flags.c_contiguous
        ):
            raise LightstageError(f"output buffers do not fit a {W}x{H} frame downscaled {factor}x")
        self._max_rows = min(band_rows, H)
        self._buf = None  # the float32 band buffer of the OpenCV path, made when first needed
        self._kernel = area_kernel.AreaKernel(W) if area_kernel.available() else None
        self._cut_bits = int(saturation_half(cutoff).view(np.int16))
        self._row = 0
        self.non_finite = self.negative = 0

    def add(self, band: np.ndarray) -> None:
        """Average the next (n, W, 3) half/float rows into the output (n a multiple of the factor)."""
        import cv2
        import torch

        f, (W, H), y = self.factor, self.size, self._row
        n = band.shape[0]
        if band.shape[1:] != (W, 3) or n % f or n > self._max_rows or y + n > H:
            raise LightstageError(f"band of shape {band.shape} does not fit a {W}x{H} frame at row {y}")
        rows = slice(y // f, (y + n) // f)
        kernel = self._kernel
        if kernel is not None and not band.flags.c_contiguous:
            band = np.ascontiguousarray(band)  # e.g. RGB of an RGBA decode: a band's copy, not a frame's
        if kernel is not None and f == 4 and band.dtype == np.float16:
            self._add_half4(kernel, band, rows)
            self._row = y + n
            return
        if f == 1:  # the identity (an SfM image at raw size): convert straight into the output
            buf = torch.from_numpy(self.rgb[rows])
            buf.copy_(torch.from_numpy(band))
        else:
            if self._buf is None:
                self._buf = torch.empty((self._max_rows, W, 3), dtype=torch.float32)
            buf = self._buf[:n]
            buf.copy_(torch.from_numpy(band))
            cv2.resize(buf.numpy(), (W // f, n // f), dst=self.rgb[rows], interpolation=cv2.INTER_AREA)
        if band.dtype == np.float16:
            # for non-negative halfs the int16 view orders like the value: no float test needed unless
            # the band reaches the cutoff (NaN bit patterns also compare high; such frames are rejected later);
            # a sign bit (int16 < 0) or an all-ones exponent (>= 0x7C00: Inf/NaN) sends the band to be counted
            bits = band.view(np.int16)
            lo, hi = (int(v) for v in torch.aminmax(torch.from_numpy(bits)))
            if hi < self._cut_bits:
                self.saturated[rows] = False
            elif kernel is not None:
                kernel.block_any_ge(band, self.saturated[rows], self._cut_bits, f)
            else:
                self.saturated[rows] = _block_any((bits >= self._cut_bits).any(axis=-1), f)
            if lo < 0 or hi >= 0x7C00:
                self._count_bad(buf)
        else:
            lo, hi = (float(v) for v in torch.aminmax(buf))
            if hi < self.cutoff:
                self.saturated[rows] = False
            elif kernel is not None and band.dtype == np.float32:
                kernel.block_any_ge(band, self.saturated[rows], self.cutoff, f)
            else:
                self.saturated[rows] = _block_any((buf.numpy() >= self.cutoff).any(axis=-1), f)
            if not (lo >= 0.0 and hi < np.inf):
                self._count_bad(buf)
        self._row = y + n

    def _add_half4(self, kernel: area_kernel.AreaKernel, band: np.ndarray, rows: slice) -> None:
        """The numba path of `add` for a contiguous half band at factor 4: the same bits as the OpenCV path."""
        lo, hi = kernel.area4_half(band, self.rgb[rows])
        if hi < self._cut_bits:
            self.saturated[rows] = False
        else:
            kernel.block_any_ge(band, self.saturated[rows], self._cut_bits, 4)
        if lo < 0 or hi >= 0x7C00:
            non_finite, negative = area_kernel.count_bad_half(band)
            self.non_finite += non_finite
            self.negative += negative

    def _count_bad(self, buf) -> None:  # noqa: ANN001 - a torch tensor
        """Count the band's NaN/Inf and negative samples (as `lightstage.frames.check_pixels` counts them)."""
        import torch

        self.non_finite += int((~torch.isfinite(buf)).sum())
        self.negative += int((buf < 0).sum())

    def result(self) -> Downscaled:
        if self._row != self.size[1]:
            raise LightstageError(f"frame ended after {self._row} of {self.size[1]} rows")
        return Downscaled(self.rgb, self.saturated, self.non_finite, self.negative)


def downscale(
    pixels: np.ndarray,
    cutoff: float,
    band_rows: int = 256,
    factor: int = DOWNSCALE,
    out: tuple[np.ndarray, np.ndarray] | None = None,
) -> Downscaled:
    """Exact `factor`x area average of (H, W, 3) half/float pixels in float32, and the saturation flags
    (a processed pixel is saturated when any channel of any of its factor^2 sources is >= cutoff); `out` as
    for `BandDownscaler`."""
    H, W, C = pixels.shape
    if H % factor or W % factor or C != 3:
        raise LightstageError(f"frame {W}x{H}x{C}: size must be a multiple of {factor} with 3 channels")
    band_rows = max(factor, band_rows - band_rows % factor)
    scaler = BandDownscaler((W, H), cutoff, band_rows, factor, out)
    pixels = np.asarray(pixels)
    for y in range(0, H, band_rows):
        scaler.add(pixels[y : y + band_rows])
    return scaler.result()


def decode_downscale(
    path: str | os.PathLike[str],
    size: tuple[int, int],
    cutoff: float,
    band_rows: int = 64,
    factor: int = DOWNSCALE,
) -> Downscaled:
    """Decode a raw frame in row bands (OpenImageIO scanline reads) and downscale each band while it is in
    cache: the same result as `downscale(decode_raw(...))` at about the cost of the decode alone, and the
    full-resolution frame is never held in memory (a few MB per band instead of 268 MB at 8192x5464).

    Header problems raise a LightstageError naming the file before any pixels are decoded, as in
    `decode_raw`; undecodable pixel data raises one naming the file and the rows.
    """
    return decode_downscale_factors(path, size, cutoff, band_rows, (factor,))[0]


def decode_downscale_factors(
    path: str | os.PathLike[str],
    size: tuple[int, int],
    cutoff: float,
    band_rows: int,
    factors: tuple[int, ...],
    out: tuple[np.ndarray, np.ndarray] | None = None,
) -> list[Downscaled]:
    """`decode_downscale` at several factors from one banded decode (the processed frame and the SfM image's
    frame of a chunk task), each exactly `downscale(decode_raw(...), factor=f)`; `out` (as for
    `BandDownscaler`) receives the first factor's."""
    import math

    import OpenImageIO as oiio

    path = Path(path)
    kind = _check_raw_header(path, size)
    W, H = size
    step = math.lcm(*factors)
    band_rows = max(step, band_rows - band_rows % step)
    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        raise LightstageError(f"{path}: cannot open ({oiio_error(oiio.geterror)})")
    try:
        spec = inp.spec()
        names = list(spec.channelnames)
        idx = [names.index(c) for c in "RGB"]
        lo, hi = min(idx), max(idx) + 1
        pick = None if idx == list(range(lo, hi)) else [i - lo for i in idx]
        y0 = spec.y
        scalers = [
            BandDownscaler(size, cutoff, band_rows, f, out if i == 0 else None) for i, f in enumerate(factors)
        ]
        for y in range(0, H, band_rows):
            n = min(band_rows, H - y)
            band = inp.read_scanlines(0, 0, y0 + y, y0 + y + n, 0, lo, hi, kind)
            if band is None or band.shape != (n, W, hi - lo):
                raise LightstageError(
                    f"{path}: corrupt EXR pixel data in rows {y}-{y + n - 1} ({oiio_error(inp.geterror)})"
                )
            band = band if pick is None else np.ascontiguousarray(band[..., pick])
            for scaler in scalers:
                scaler.add(band)
        return [scaler.result() for scaler in scalers]
    finally:
        inp.close()


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
