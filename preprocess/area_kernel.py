"""The downscale's CPU kernels in numba: the 4x area average of half RGB rows and the per-block saturation test.

`area4_half` gives exactly what the PyTorch half -> float32 copy plus `cv2.resize(INTER_AREA)` gives (OpenCV's
integer-factor path adds each source row's 4 samples left to right, adds the rows' sums to a running sum that
starts at 0, and scales by 1/16), without the band's float32 copy and 3.3x faster (docs/benchmarks.md).
`block_any_ge` replaces a numpy any-reduction that cost ~1 CPU-s per 8192x5464 frame whose bands all reach the
saturation cutoff (real captures' highlights do) with ~0.005 s. Without numba (or with
`LIGHTSTAGE_AREA_KERNEL=cv2`) `preprocess.downscale` keeps its PyTorch/OpenCV/numpy path: the same bits.
"""

from __future__ import annotations

import numpy as np

from lightstage.kernel_switch import KernelSwitch

try:
    import numba
    from llvmlite import ir
    from numba.core import types
    from numba.extending import intrinsic
except ImportError:  # pragma: no cover - numba is a dependency; the OpenCV path still works without it
    numba = None

_SWITCH = KernelSwitch("LIGHTSTAGE_AREA_KERNEL", "cv2", numba is not None)
available = _SWITCH.available  # numba importable and not switched off
set_enabled = _SWITCH.set_enabled  # tests and benches compare both paths


def count_bad_half(bits: np.ndarray) -> tuple[int, int]:
    """(NaN/Inf, negative) sample counts of half bit patterns (uint16), as `torch.isfinite` / `< 0` count the
    values: an all-ones exponent is non-finite; negative means a sign bit on a non-zero, non-NaN value."""
    u = bits.view(np.uint16)
    non_finite = int(np.count_nonzero((u & 0x7C00) == 0x7C00))
    negative = int(np.count_nonzero((u > 0x8000) & (u <= 0xFC00)))
    return non_finite, negative


if numba is not None:

    @intrinsic
    def _half_to_float(typingctx, bits):
        """The float32 value of a half's bit pattern (LLVM's fpext: one vcvtph2ps lane on F16C CPUs; exact)."""
        sig = types.float32(types.uint16)

        def codegen(context, builder, signature, args):
            return builder.fpext(builder.bitcast(args[0], ir.HalfType()), ir.FloatType())

        return sig, codegen

    @numba.njit(nogil=True, cache=True)
    def _area4_half(src, dst, planes, acc):  # pragma: no cover - compiled; tests compare it with OpenCV
        """dst (n/4, 3W/4) = 4x area average of src (n, 3W) half RGB bits; returns the band's min and max
        bits as int16 (for non-negative halfs the int16 order is the value order). Each row is split into
        float32 planes first, so every loop below runs over contiguous or small-stride data (SIMD)."""
        n, w3 = src.shape
        wi = w3 // 3
        wo = wi // 4
        lo = np.int16(32767)
        hi = np.int16(-32768)
        sixteenth = np.float32(0.0625)
        for oy in range(n // 4):
            for c in range(3):
                for ox in range(wo):
                    acc[c, ox] = np.float32(0.0)
            for k in range(4):
                row = src[4 * oy + k]
                for x in range(wi):
                    planes[0, x] = _half_to_float(row[3 * x])
                    planes[1, x] = _half_to_float(row[3 * x + 1])
                    planes[2, x] = _half_to_float(row[3 * x + 2])
                for j in range(w3):
                    v = np.int16(row[j])
                    lo = min(lo, v)
                    hi = max(hi, v)
                for c in range(3):
                    p = planes[c]
                    a = acc[c]
                    for ox in range(wo):
                        a[ox] += ((p[4 * ox] + p[4 * ox + 1]) + p[4 * ox + 2]) + p[4 * ox + 3]
            d = dst[oy]
            for ox in range(wo):
                d[3 * ox] = acc[0, ox] * sixteenth
                d[3 * ox + 1] = acc[1, ox] * sixteenth
                d[3 * ox + 2] = acc[2, ox] * sixteenth
        return lo, hi

    @numba.njit(nogil=True, cache=True)
    def _block_any_ge(src, out, cut, factor, rows, pixels):  # pragma: no cover - compiled; tests compare
        """out (n/f, W/f) = any of a block's f x f x 3 samples of src (n, 3W) >= cut (int16 half bits or
        float32 values: NaN compares False). The rows are OR-ed first, then the pixels' channels, then f
        pixels: each a contiguous or small-stride loop."""
        n, w3 = src.shape
        wi = w3 // 3
        wo = wi // factor
        for oy in range(n // factor):
            for j in range(w3):
                rows[j] = src[factor * oy, j] >= cut
            for k in range(1, factor):
                r = src[factor * oy + k]
                for j in range(w3):
                    rows[j] |= r[j] >= cut
            for x in range(wi):
                pixels[x] = rows[3 * x] | rows[3 * x + 1] | rows[3 * x + 2]
            o = out[oy]
            for ox in range(wo):
                any_ = pixels[factor * ox]
                for t in range(1, factor):
                    any_ |= pixels[factor * ox + t]
                o[ox] = any_


class AreaKernel:
    """Scratch rows for the kernels at one frame width (reused across bands and frames: no per-band memory)."""

    def __init__(self, width: int) -> None:
        self.width = width
        self._planes = np.empty((3, width), np.float32)
        self._acc = np.empty((3, width // 4), np.float32)
        self._rows = np.empty(3 * width, np.bool_)
        self._pixels = np.empty(width, np.bool_)

    def area4_half(self, band: np.ndarray, dst: np.ndarray) -> tuple[int, int]:
        """dst (n/4, W/4, 3) float32 = the 4x area average of a C-contiguous (n, W, 3) half band; returns
        the band's (min, max) as int16 bit patterns."""
        n = band.shape[0]
        lo, hi = _area4_half(
            band.view(np.uint16).reshape(n, -1), dst.reshape(n // 4, -1), self._planes, self._acc
        )
        return int(lo), int(hi)

    def block_any_ge(self, band: np.ndarray, out: np.ndarray, cut: int | float, factor: int) -> None:
        """out (n/f, W/f) bool = any sample of each f x f block of a C-contiguous (n, W, 3) band >= cut (a half
        band compares its int16 bits with an int16 `cut`, a float32 band its values)."""
        n = band.shape[0]
        src = band.view(np.int16) if band.dtype == np.float16 else band
        cut = np.int16(cut) if band.dtype == np.float16 else np.float32(cut)  # numpy (NEP 50) compares so
        _block_any_ge(src.reshape(n, -1), out, cut, factor, self._rows, self._pixels)
