"""The downscale's numba kernels (preprocess/area_kernel.py) give the bits of the PyTorch/OpenCV/numpy path."""

from __future__ import annotations

import numpy as np
import pytest

from lightstage.preprocess import area_kernel
from lightstage.preprocess.downscale import BandDownscaler, downscale

SPECIAL = np.array(
    [0x0000, 0x8000, 0x0001, 0x03FF, 0x0400, 0x7BFF, 0x7C00, 0xFC00, 0x7E00, 0xFE00, 0x7C01, 0x8001, 0x3C00],
    np.uint16,
)


def _both(pixels: np.ndarray, cutoff: float, band_rows: int = 64, factor: int = 4):
    """downscale with the kernels and without them (the OpenCV path)."""
    fast = downscale(pixels, cutoff, band_rows, factor)
    old = area_kernel.set_enabled(False)
    try:
        slow = downscale(pixels, cutoff, band_rows, factor)
    finally:
        area_kernel.set_enabled(old)
    return fast, slow


def _assert_same(fast, slow) -> None:
    finite = np.isfinite(slow.rgb)
    np.testing.assert_array_equal(np.isfinite(fast.rgb), finite)
    # every finite mean bit for bit (NaN payloads are not compared: such frames are refused)
    np.testing.assert_array_equal(fast.rgb.view(np.uint32)[finite], slow.rgb.view(np.uint32)[finite])
    np.testing.assert_array_equal(fast.saturated, slow.saturated)
    assert (fast.non_finite, fast.negative) == (slow.non_finite, slow.negative)


def test_the_kernels_are_the_path_that_runs() -> None:
    """numba is a dependency: a silent fall-back to the slow path would lose the speed without a failure."""
    assert area_kernel.available()
    assert BandDownscaler((16, 8), 1.0, 8)._kernel is not None


@pytest.mark.parametrize("width", [4, 12, 100, 1028])
@pytest.mark.parametrize("cutoff", [0.5, 30.0, 60000.0])
def test_half_area_average_is_opencv_bit_for_bit(width: int, cutoff: float) -> None:
    rng = np.random.default_rng(width)
    scale = rng.choice([1e-7, 1e-4, 1e-2, 1.0, 300.0], (32, width, 3))
    px = (rng.exponential(0.6, (32, width, 3)) * scale).astype(np.float16)
    fast, slow = _both(px, cutoff, band_rows=8)
    assert slow.saturated.any() == (cutoff < 60000.0)
    _assert_same(fast, slow)


def test_special_half_values_negative_and_non_finite_counts() -> None:
    rng = np.random.default_rng(1)
    bits = rng.integers(0, 0x7C00, (16, 40, 3), dtype=np.uint16)
    bits.reshape(-1)[rng.choice(bits.size, 400, replace=False)] = rng.choice(SPECIAL, 400)
    fast, slow = _both(bits.view(np.float16), 2.0, band_rows=8)
    assert slow.non_finite > 0 and slow.negative > 0
    _assert_same(fast, slow)
    # a band with only signed zeros and sub-normals: no bad samples, -0 is not negative
    zeros = np.array([0x8000, 0x0000, 0x8001, 0x0001], np.uint16)[rng.integers(0, 4, (8, 8, 3))]
    fast, slow = _both(zeros.view(np.float16), 2.0)
    _assert_same(fast, slow)


def test_float_frames_and_strided_bands_and_other_factors() -> None:
    rng = np.random.default_rng(2)
    px = rng.exponential(1.0, (24, 36, 4)).astype(np.float32)
    for pixels in (px[..., :3], px[..., :3].astype(np.float16)):  # strided RGB of an RGBA decode
        for factor in (1, 2, 3, 4):
            _assert_same(*_both(pixels, 1.5, band_rows=12, factor=factor))
    count = BandDownscaler((36, 24), 1.5, 12)
    count.add(np.full((12, 36, 3), np.nan, np.float32))
    assert count.non_finite == 12 * 36 * 3


def test_the_environment_switches_the_kernels_off(monkeypatch: pytest.MonkeyPatch) -> None:
    from lightstage.kernel_switch import KernelSwitch

    monkeypatch.setenv("LIGHTSTAGE_AREA_KERNEL", "cv2")
    assert not KernelSwitch("LIGHTSTAGE_AREA_KERNEL", "cv2", True).available()
    monkeypatch.setenv("LIGHTSTAGE_AREA_KERNEL", "numba")
    switch = KernelSwitch("LIGHTSTAGE_AREA_KERNEL", "cv2", True)
    assert switch.available() and not KernelSwitch("X", "off", False).available()
    assert switch.set_enabled(False) is True and not switch.available()


def test_float_saturation_compares_with_the_cutoff_as_given() -> None:
    """At the cutoff's float32 rounding (below the cutoff here) the kernel decides as the numpy path did: numpy
    compares a float32 array with a Python float in float32 (NEP 50), so that sample counts as saturated."""
    cutoff = 4.4019
    below = np.float32(cutoff)
    assert float(below) < cutoff
    px = np.zeros((8, 8, 3), np.float32)
    px[1, 1, 0] = below
    px[5, 5, 2] = np.nextafter(below, np.float32(10))
    fast, slow = _both(px, cutoff, band_rows=8)
    _assert_same(fast, slow)
    assert fast.saturated.tolist() == [[True, False], [False, True]]
