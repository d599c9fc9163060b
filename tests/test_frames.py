"""HDR frame I/O: bit-exact EXR round trips, attributes, clear errors on damaged files."""

from __future__ import annotations

import numpy as np
import pytest

from lightstage.errors import LightstageError
from lightstage.exr_header import read_exr_header
from lightstage.frames import read_exr, read_image, write_exr, write_exr_planes, write_image


@pytest.mark.parametrize("half", [True, False])
@pytest.mark.parametrize("compression", ["zip", "piz"])
@pytest.mark.parametrize("nch", [3, 4])
def test_exr_round_trip_bit_exact(tmp_path, half, compression, nch):
    rng = np.random.default_rng(1)
    dtype = np.float16 if half else np.float32
    img = (rng.standard_normal((37, 53, nch)) * 100).astype(dtype)
    img[0, 0, 0] = 65504 if half else 1e30
    path = tmp_path / "f.exr"
    write_exr(path, img, half=half, compression=compression, attributes={"source": "unit test", "gain": 2.5})
    back = read_exr(path, channels="RGBA"[:nch])
    assert back.dtype == dtype
    assert np.array_equal(
        back.view(np.uint16 if half else np.uint32), img.view(np.uint16 if half else np.uint32)
    )
    h = read_exr_header(path)
    assert (h.width, h.height) == (53, 37)
    assert h.compression == compression
    assert h.dtype == ("half" if half else "float")
    assert h.attributes["source"] == "unit test"
    assert h.attributes["gain"] == pytest.approx(2.5)


def test_non_contiguous_input_written_correctly(tmp_path):
    img = np.random.default_rng(2).random((20, 30, 4)).astype(np.float32)
    view = img[:, :, 1:]  # non-contiguous
    write_exr(tmp_path / "v.exr", view, half=False)
    assert np.array_equal(read_exr(tmp_path / "v.exr"), view)


def test_wrong_size_is_rejected_before_decoding(tmp_path):
    write_exr(tmp_path / "f.exr", np.zeros((10, 12, 3)))
    with pytest.raises(LightstageError, match="resolution 12x10, expected 16x10"):
        read_exr(tmp_path / "f.exr", expected_size=(16, 10))


def test_missing_channel_and_missing_file(tmp_path):
    write_exr(tmp_path / "y.exr", np.zeros((4, 4, 1)))
    with pytest.raises(LightstageError, match="missing channel"):
        read_exr(tmp_path / "y.exr")
    with pytest.raises(LightstageError, match="file not found"):
        read_exr(tmp_path / "nope.exr")


def test_truncated_and_garbage_files(tmp_path):
    path = tmp_path / "f.exr"
    write_exr(path, np.random.default_rng(3).random((64, 64, 3)))
    data = path.read_bytes()
    (tmp_path / "t.exr").write_bytes(data[: len(data) // 2])
    (tmp_path / "g.exr").write_bytes(b"not an exr at all" * 10)
    (tmp_path / "e.exr").write_bytes(b"")
    for name in ("t.exr", "g.exr", "e.exr"):
        with pytest.raises(LightstageError) as err:
            read_exr(tmp_path / name)
        assert name in str(err.value)


def test_other_formats_through_openimageio(tmp_path):
    img = np.random.default_rng(4).random((8, 9, 3)).astype(np.float32)
    write_image(tmp_path / "a.hdr", img)
    # RGBE shares one exponent per pixel: error is relative to the largest channel (8-bit mantissa)
    np.testing.assert_allclose(
        read_image(tmp_path / "a.hdr"), img, atol=img.max(axis=-1, keepdims=True).max() / 128
    )
    u8 = (img * 255).astype(np.uint8)
    write_image(tmp_path / "a.png", u8)
    np.testing.assert_allclose(read_image(tmp_path / "a.png"), u8 / 255.0, atol=1e-6)
    write_image(tmp_path / "a.tif", img)
    np.testing.assert_allclose(read_image(tmp_path / "a.tif"), img)


def test_exr_writers_leave_the_callers_planes_alone(tmp_path):
    """OpenEXR's bindings swap the arrays of the dict they get for Channel objects; ours must not leak that."""
    from lightstage.frames import ExrPart, write_exr_parts

    planes = {c: np.full((5, 7), i, np.float16) for i, c in enumerate("RGB")}
    write_exr_planes(tmp_path / "a.exr", planes, compression="rle")
    write_exr_parts(
        tmp_path / "b.exr", [ExrPart("rgb", planes, "none"), ExrPart("s", {"S": planes["R"]}, "rle")]
    )
    assert all(isinstance(p, np.ndarray) for p in planes.values())
    write_exr_planes(tmp_path / "c.exr", planes, compression="zip")  # the same dict again
