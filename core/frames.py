"""HDR frame I/O: OpenEXR for EXR (half/float, RGB/RGBA, ZIP/PIZ, provenance attributes), OpenImageIO for
other formats (Radiance HDR, TIFF, PNG). Every failure is a LightstageError naming the file.

EXR headers are parsed here in pure Python (bounded reads, no native code), so a hostile file is refused
before any native decoder sees it: the data window is checked against the expected resolution and a
pixel/byte ceiling, the chunk offset table against the file size (truncation), channel types and sampling
against what `read_exr` can return. Only then does OpenEXR decode the pixels.
"""

from __future__ import annotations

import errno
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from lightstage.atomic import atomic_path
from lightstage.errors import LightstageError
from lightstage.exr_header import (
    EXR_MAGIC,
    MAX_DECODE_BYTES,
    MAX_PIXELS,
    MAX_SIDE,
    check_exr_header,
    first_line,
    read_exr_header,
    reason,
)

COMPRESSIONS = ("zip", "piz", "rle", "none")  # lossless only: never DWA for data
PNG_COMPRESSION_LEVEL = 3
PNG_END = b"IEND\xaeB`\x82"  # the last 8 bytes of every PNG: the IEND chunk's type and CRC


# No frame of a supported stage is larger than this (8192x5464 is 44.8 Mpx); guards hostile headers.
def _exr_compression(name: str) -> Any:
    import OpenEXR

    table = {
        "zip": OpenEXR.ZIP_COMPRESSION,
        "piz": OpenEXR.PIZ_COMPRESSION,
        "rle": OpenEXR.RLE_COMPRESSION,
        "none": OpenEXR.NO_COMPRESSION,
    }
    if name not in table:
        raise LightstageError(f"unsupported EXR compression {name!r} (use one of {', '.join(COMPRESSIONS)})")
    return table[name]


def set_exr_limits() -> None:
    """OpenEXR's own size guards (a second line of defence behind check_exr_header)."""
    import OpenEXR

    if OpenEXR.getMaxImageSize() != (MAX_SIDE, MAX_SIDE):
        OpenEXR.setMaxImageSize(MAX_SIDE, MAX_SIDE)
        OpenEXR.setMaxTileSize(MAX_SIDE, MAX_SIDE)


def read_exr(
    path: str | os.PathLike[str],
    expected_size: tuple[int, int] | None = None,
    channels: str = "RGB",
) -> np.ndarray:
    """Decode an EXR into an (H, W, len(channels)) array of its stored dtype (float16 or float32).

    `expected_size` = (width, height): a mismatch is an error before decoding. Missing channels are an error.
    The header is parsed and checked (check_exr_header) before OpenEXR sees the pixels.
    """
    import OpenEXR

    header = read_exr_header(path)
    check_exr_header(header, expected_size, channels)
    set_exr_limits()
    try:
        f = OpenEXR.File(str(header.path), separate_channels=True)
        planes = f.parts[0].channels
        arrays = [planes[c].pixels for c in channels]
    except (IndexError, KeyError):  # the bindings print the decoder's error and return no pixels
        raise LightstageError(
            f"{header.path}: corrupt EXR pixel data (chunks could not be decoded)"
        ) from None
    except Exception as e:
        raise LightstageError(f"{header.path}: corrupt EXR pixel data ({reason(e)})") from None
    dtypes = {a.dtype for a in arrays}
    if len(dtypes) != 1 or next(iter(dtypes)) not in (np.float16, np.float32):
        raise LightstageError(
            f"{header.path}: channels must all be half or all float, got {sorted(map(str, dtypes))}"
        )
    if any(a.shape != (header.height, header.width) for a in arrays):
        raise LightstageError(
            f"{header.path}: decoded {arrays[0].shape[1]}x{arrays[0].shape[0]}, "
            f"header says {header.width}x{header.height}"
        )
    return np.stack(arrays, axis=-1)


@dataclass(frozen=True)
class PixelCheck:
    """Result of check_pixels: status 'ok' | 'non_finite' | 'negative', a message and the counts."""

    status: str
    message: str
    non_finite: int = 0
    negative: int = 0
    saturated_fraction: float = 0.0

    @property
    def ok(self) -> bool:
        return self.status == "ok"


def check_pixels(pixels: np.ndarray, saturation: float | None = None, rows_per_band: int = 256) -> PixelCheck:
    """Count non-finite and negative samples (and, given the stage's cutoff, the saturated fraction) of an
    (H, W, C) image, in row bands so a full-resolution frame needs no full-size temporaries."""
    non_finite = negative = saturated = 0
    for r in range(0, pixels.shape[0], rows_per_band):
        band = np.asarray(pixels[r : r + rows_per_band], dtype=np.float32)
        finite = np.isfinite(band)
        non_finite += int(band.size - np.count_nonzero(finite))
        negative += int(np.count_nonzero(band < 0))
        if saturation is not None:
            saturated += int(
                np.count_nonzero((band >= saturation).any(axis=-1) if band.ndim == 3 else band >= saturation)
            )
    npx = pixels.shape[0] * pixels.shape[1]
    return pixel_verdict(non_finite, negative, saturated / npx if npx else 0.0)


def pixel_verdict(non_finite: int, negative: int, saturated_fraction: float = 0.0) -> PixelCheck:
    """The one pixel policy, applied by `validate --deep` (check_pixels) and preprocess alike: a raw frame with
    any NaN/Inf sample, or any negative sample, is rejected (a content error: the frame is bad and unused);
    nothing is clamped. Radiance is never negative, so negatives mean a broken black-level subtraction or
    a foreign file, which should be fixed upstream rather than averaged into the processed frames."""
    if non_finite:
        return PixelCheck(
            "non_finite", f"{non_finite} NaN/Inf samples", non_finite, negative, saturated_fraction
        )
    if negative:
        return PixelCheck(
            "negative", f"{negative} negative samples", non_finite, negative, saturated_fraction
        )
    return PixelCheck("ok", "", 0, 0, saturated_fraction)


def write_exr(
    path: str | os.PathLike[str],
    pixels: np.ndarray,
    *,
    half: bool = True,
    compression: str = "zip",
    attributes: dict[str, str | float | int] | None = None,
    channels: str | None = None,
) -> None:
    """Write an (H, W, C) image as a scanline EXR, atomically. C = 3 (RGB), 4 (RGBA) or 1 (Y).

    String/float/int attributes are stored for provenance (floats become 32-bit in the header).
    """
    pixels = np.asarray(pixels)
    if pixels.ndim == 2:
        pixels = pixels[..., None]
    names = channels or {1: "Y", 3: "RGB", 4: "RGBA"}.get(pixels.shape[-1])
    if names is None or len(names) != pixels.shape[-1]:
        raise LightstageError(f"{path}: cannot write an image with {pixels.shape[-1]} channels as EXR")
    dtype = np.float16 if half else np.float32
    planes = {n: np.ascontiguousarray(pixels[..., i], dtype=dtype) for i, n in enumerate(names)}
    write_exr_planes(path, planes, compression=compression, attributes=attributes)


def write_exr_planes(
    path: str | os.PathLike[str],
    planes: dict[str, np.ndarray],
    *,
    compression: str = "zip",
    attributes: dict[str, str | float | int] | None = None,
) -> None:
    """Write named (H, W) half/float planes as a scanline EXR, atomically, without repacking them."""
    write_exr_parts(path, [ExrPart("", planes, compression)], attributes=attributes)


@dataclass(frozen=True)
class ExrPart:
    """One part of an EXR file: its name (unused for single-part files), planes and compression."""

    name: str
    planes: dict[str, np.ndarray]
    compression: str


def write_exr_parts(
    path: str | os.PathLike[str],
    parts: list[ExrPart],
    *,
    tile: int | None = None,
    attributes: dict[str, str | float | int] | None = None,
) -> None:
    """Write an EXR of one or more parts atomically, scanline or in `tile` x `tile` tiles; `attributes` go in
    the first part's header.

    Each part has its own compression, so e.g. noisy colour planes can go uncompressed next to RLE flags.
    Tiles make few large chunks: OpenEXR's per-chunk cost dominates an uncompressed scanline write.
    The bindings silently write wrong pixels from non-contiguous arrays, so every plane must be C-contiguous.
    """
    import OpenEXR

    headers = []
    for part in parts:
        for name, plane in part.planes.items():
            if plane.ndim != 2 or not plane.flags.c_contiguous or plane.dtype not in (np.float16, np.float32):
                raise LightstageError(
                    f"{path}: EXR plane {name!r} must be a C-contiguous 2-D half/float array, "
                    f"got {plane.dtype} {plane.shape}"
                )
        header: dict[str, Any] = {"compression": _exr_compression(part.compression)}
        if tile is None:
            header["type"] = OpenEXR.scanlineimage
        else:
            tiles = OpenEXR.TileDescription()
            tiles.xSize = tiles.ySize = tile
            tiles.mode = OpenEXR.ONE_LEVEL
            header.update(type=OpenEXR.tiledimage, tiles=tiles)
        headers.append(header)
    for k, v in (attributes or {}).items():
        headers[0][k] = v if isinstance(v, str) else float(v)
    with atomic_path(path) as tmp:
        try:
            # The bindings replace the arrays of the dict they are given with Channel objects: hand them copies.
            if len(parts) == 1:
                exr = OpenEXR.File(headers[0], dict(parts[0].planes))
            else:
                exr = OpenEXR.File(
                    [
                        OpenEXR.Part(h, dict(p.planes), name=p.name)
                        for h, p in zip(headers, parts, strict=True)
                    ]
                )
            exr.write(str(tmp))
        except Exception as e:
            raise LightstageError(f"{path}: cannot write EXR ({reason(e)})") from None


def read_image(path: str | os.PathLike[str], expected_size: tuple[int, int] | None = None) -> np.ndarray:
    """Read any supported image as float32 (H, W, C): EXR through OpenEXR, others through OpenImageIO."""
    path = Path(path)
    if path.suffix.lower() == ".exr" or _has_exr_magic(path):
        return read_exr(path, expected_size).astype(np.float32)
    import OpenImageIO as oiio

    _check_file(path)
    oiio.attribute("limits:imagesize_MB", MAX_DECODE_BYTES >> 20)  # OIIO's own guard, behind ours
    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        raise LightstageError(f"{path}: cannot open image ({oiio_error(oiio.geterror) or 'unknown format'})")
    try:
        spec = inp.spec()
        if spec.width * spec.height > MAX_PIXELS:
            raise LightstageError(f"{path}: {spec.width}x{spec.height} exceeds the {MAX_PIXELS} pixel limit")
        if expected_size and (spec.width, spec.height) != tuple(expected_size):
            raise LightstageError(
                f"{path}: resolution {spec.width}x{spec.height}, expected {expected_size[0]}x{expected_size[1]}"
            )
        data = inp.read_image(0, 0, 0, spec.nchannels, "float")
        if data is None:
            raise LightstageError(f"{path}: cannot decode image ({oiio_error(inp.geterror)})")
    finally:
        inp.close()
    return np.asarray(data, dtype=np.float32).reshape(spec.height, spec.width, spec.nchannels)


def write_image(path: str | os.PathLike[str], pixels: np.ndarray) -> None:
    """Write a non-EXR image (PNG/TIFF/HDR/JPEG) through OpenImageIO, atomically. uint8 stays 8-bit."""
    import OpenImageIO as oiio

    pixels = np.ascontiguousarray(pixels)
    if pixels.ndim == 2:
        pixels = pixels[..., None]
    fmt = "uint8" if pixels.dtype == np.uint8 else "float"
    spec = oiio.ImageSpec(pixels.shape[1], pixels.shape[0], pixels.shape[2], fmt)
    if Path(path).suffix.lower() == ".png":
        # zlib level 3 instead of 6: +3% size on noisy previews, 2.5x faster (0.24 s vs 0.63 s at 2048x1366)
        spec.attribute("png:compressionLevel", PNG_COMPRESSION_LEVEL)
    with atomic_path(path) as tmp:
        out = oiio.ImageOutput.create(str(path))
        if out is None or not out.open(str(tmp), spec):
            raise LightstageError(f"{path}: cannot write image ({oiio_error(oiio.geterror)})")
        ok = out.write_image(pixels)
        out.close()
        if not ok:
            raise LightstageError(f"{path}: cannot write image ({oiio_error(out.geterror)})")
        _check_written(tmp, path)


def write_png(path: str | os.PathLike[str], pixels: np.ndarray) -> None:
    """Write an 8-bit grey (h, w) or RGB (h, w, 3) image as PNG through OpenCV's encoder, atomically. The
    pixels read back exactly as from `lightstage.frames.write_image`; only the compression differs: zlib level 1
    with run-length matching only and the "up" row filter. The demo's 768x512 SfM image takes 17 ms and
    468 kB so, against 71 ms and 509 kB through OpenImageIO at level 3; a mask 0.8 ms (docs/benchmarks.md)."""
    import cv2

    from lightstage.atomic import write_bytes_atomic

    if pixels.dtype != np.uint8 or pixels.ndim not in (2, 3) or (pixels.ndim == 3 and pixels.shape[2] != 3):
        raise LightstageError(f"{path}: expected 8-bit grey or RGB pixels, got {pixels.dtype} {pixels.shape}")
    params = [
        *(cv2.IMWRITE_PNG_COMPRESSION, 1),
        *(cv2.IMWRITE_PNG_STRATEGY, cv2.IMWRITE_PNG_STRATEGY_RLE),
        *(cv2.IMWRITE_PNG_FILTER, cv2.IMWRITE_PNG_FILTER_UP),
    ]
    ok, data = cv2.imencode(".png", pixels[..., ::-1] if pixels.ndim == 3 else pixels, params)
    if not ok:
        raise LightstageError(f"{path}: cannot encode PNG")
    write_bytes_atomic(path, data.tobytes())


def _check_written(tmp: Path, path: str | os.PathLike[str]) -> None:
    """OpenImageIO reports success when its writes fail (a full disk leaves an empty or cut file): a written
    image must be non-empty and a PNG must end with its IEND chunk. Otherwise an OSError naming `path`:
    ENOSPC when the disk is full, EIO else."""
    size = tmp.stat().st_size
    whole = size > 0
    if whole and tmp.suffix.lower() == ".png":
        with tmp.open("rb") as f:
            f.seek(max(0, size - len(PNG_END)))
            whole = f.read() == PNG_END
    if whole:
        return
    fs = os.statvfs(tmp.parent)
    code = errno.ENOSPC if fs.f_bavail * fs.f_frsize < (1 << 20) else errno.EIO
    raise OSError(code, f"{os.strerror(code)} (image write cut at {size} bytes)", os.fspath(path))


def _has_exr_magic(path: Path) -> bool:
    """True when the file starts with the EXR magic number (EXR content under another name)."""
    try:
        with path.open("rb") as f:
            return f.read(4) == EXR_MAGIC
    except OSError:
        return False


def oiio_error(getter: Any) -> str:
    """First line of an OpenImageIO error; its bindings raise on messages that are not valid UTF-8."""
    try:
        return first_line(getter())
    except UnicodeDecodeError:
        return "error message is not valid UTF-8"


def _check_file(path: Path) -> None:
    if not path.is_file():
        raise LightstageError(f"{path}: file not found")
    if path.stat().st_size == 0:
        raise LightstageError(f"{path}: empty file")
