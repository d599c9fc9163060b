"""HDR frame I/O: OpenEXR for EXR (half/float, RGB/RGBA, ZIP/PIZ, provenance attributes), OpenImageIO for
other formats (Radiance HDR, TIFF, PNG). Every failure is a LightstageError naming the file.

The header's data window is checked against the expected resolution (or a pixel-count ceiling) before any
pixels are decoded, so a hostile header cannot trigger a multi-GB allocation.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from lightstage.atomic import atomic_path
from lightstage.errors import LightstageError

# No frame of a supported stage is larger than this (8192x5464 is 44.8 Mpx); guards hostile headers.
MAX_PIXELS = 16384 * 16384
COMPRESSIONS = ("zip", "piz", "none")


@dataclass(frozen=True)
class FrameHeader:
    """What an image header says, read without decoding pixels."""

    path: Path
    width: int
    height: int
    channels: dict[str, str]  # name -> 'half' | 'float' | 'uint'
    compression: str
    attributes: dict[str, Any] = field(default_factory=dict)

    @property
    def dtype(self) -> str:
        kinds = set(self.channels.values())
        return kinds.pop() if len(kinds) == 1 else "mixed"


def _exr_compression(name: str) -> Any:
    import OpenEXR

    table = {"zip": OpenEXR.ZIP_COMPRESSION, "piz": OpenEXR.PIZ_COMPRESSION, "none": OpenEXR.NO_COMPRESSION}
    if name not in table:
        raise LightstageError(f"unsupported EXR compression {name!r} (use one of {', '.join(COMPRESSIONS)})")
    return table[name]


def read_exr_header(path: str | os.PathLike[str]) -> FrameHeader:
    """Parse an EXR header only (fast: no pixel decoding), through OpenImageIO's spec."""
    import OpenImageIO as oiio

    path = Path(path)
    _check_file(path)
    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        raise LightstageError(f"{path}: not a readable EXR header ({_first_line(oiio.geterror())})")
    try:
        if inp.format_name() != "openexr":
            raise LightstageError(f"{path}: not an EXR file (looks like {inp.format_name()})")
        spec = inp.spec()
        formats = spec.channelformats or [spec.format] * spec.nchannels
        channels = {
            n: _TYPE_NAMES.get(str(f), str(f)) for n, f in zip(spec.channelnames, formats, strict=True)
        }
        attributes = {a.name: a.value for a in spec.extra_attribs if isinstance(a.value, str | int | float)}
        compression = str(spec.getattribute("compression") or "unknown")
        width, height = spec.width, spec.height
    finally:
        inp.close()
    if width <= 0 or height <= 0:
        raise LightstageError(f"{path}: invalid data window {width}x{height}")
    return FrameHeader(path, width, height, channels, compression, attributes)


_TYPE_NAMES = {"half": "half", "float": "float", "uint": "uint", "uint32": "uint"}


def read_exr(
    path: str | os.PathLike[str],
    expected_size: tuple[int, int] | None = None,
    channels: str = "RGB",
) -> np.ndarray:
    """Decode an EXR into an (H, W, len(channels)) array of its stored dtype (float16 or float32).

    `expected_size` = (width, height): a mismatch is an error before decoding. Missing channels are an error.
    """
    import OpenEXR

    header = read_exr_header(path)
    _check_size(header, expected_size)
    missing = [c for c in channels if c not in header.channels]
    if missing:
        raise LightstageError(
            f"{header.path}: missing channel(s) {', '.join(missing)} (has {', '.join(sorted(header.channels))})"
        )
    try:
        f = OpenEXR.File(str(header.path), separate_channels=True)
        planes = f.parts[0].channels
        arrays = [planes[c].pixels for c in channels]
    except Exception as e:
        raise LightstageError(f"{header.path}: corrupt EXR pixel data ({_reason(e)})") from None
    dtypes = {a.dtype for a in arrays}
    if len(dtypes) != 1 or next(iter(dtypes)) not in (np.float16, np.float32):
        raise LightstageError(
            f"{header.path}: channels must all be half or all float, got {sorted(map(str, dtypes))}"
        )
    out = np.stack(arrays, axis=-1)
    if out.shape[:2] != (header.height, header.width):
        raise LightstageError(
            f"{header.path}: decoded {out.shape[1]}x{out.shape[0]}, header says {header.width}x{header.height}"
        )
    return out


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
    import OpenEXR

    pixels = np.asarray(pixels)
    if pixels.ndim == 2:
        pixels = pixels[..., None]
    names = channels or {1: "Y", 3: "RGB", 4: "RGBA"}.get(pixels.shape[-1])
    if names is None or len(names) != pixels.shape[-1]:
        raise LightstageError(f"{path}: cannot write an image with {pixels.shape[-1]} channels as EXR")
    dtype = np.float16 if half else np.float32
    # The bindings silently write wrong pixels from non-contiguous arrays: copy every plane contiguously.
    planes = {n: np.ascontiguousarray(pixels[..., i], dtype=dtype) for i, n in enumerate(names)}
    header: dict[str, Any] = {"compression": _exr_compression(compression), "type": OpenEXR.scanlineimage}
    for k, v in (attributes or {}).items():
        header[k] = v if isinstance(v, str) else float(v)
    with atomic_path(path) as tmp:
        try:
            OpenEXR.File(header, planes).write(str(tmp))
        except Exception as e:
            raise LightstageError(f"{path}: cannot write EXR ({_reason(e)})") from None


def read_image(path: str | os.PathLike[str], expected_size: tuple[int, int] | None = None) -> np.ndarray:
    """Read any supported image as float32 (H, W, C): EXR through OpenEXR, others through OpenImageIO."""
    path = Path(path)
    if path.suffix.lower() == ".exr":
        return read_exr(path, expected_size).astype(np.float32)
    import OpenImageIO as oiio

    _check_file(path)
    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        raise LightstageError(f"{path}: cannot open image ({oiio.geterror() or 'unknown format'})")
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
            raise LightstageError(f"{path}: cannot decode image ({inp.geterror()})")
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
    with atomic_path(path) as tmp:
        out = oiio.ImageOutput.create(str(path))
        if out is None or not out.open(str(tmp), spec):
            raise LightstageError(f"{path}: cannot write image ({oiio.geterror()})")
        ok = out.write_image(pixels)
        out.close()
        if not ok:
            raise LightstageError(f"{path}: cannot write image ({out.geterror()})")


def _check_file(path: Path) -> None:
    if not path.is_file():
        raise LightstageError(f"{path}: file not found")
    if path.stat().st_size == 0:
        raise LightstageError(f"{path}: empty file")


def _check_size(header: FrameHeader, expected: tuple[int, int] | None) -> None:
    if header.width * header.height > MAX_PIXELS:
        raise LightstageError(
            f"{header.path}: data window {header.width}x{header.height} exceeds the pixel limit"
        )
    if expected is not None and (header.width, header.height) != tuple(expected):
        raise LightstageError(
            f"{header.path}: resolution {header.width}x{header.height}, expected {expected[0]}x{expected[1]}"
        )


def _reason(e: BaseException) -> str:
    return _first_line(str(e)) or type(e).__name__


def _first_line(text: str) -> str:
    lines = (text or "").strip().splitlines()
    return lines[0][:200] if lines else ""
