"""The processed frame on disk (WorkDir.frame): half EXR with channels R, G, B and S (1 = saturated source).

Layout: two parts in 256x256 tiles, "rgb" (R, G, B, the stage config's compression) and "saturation" (S, RLE).
Noisy HDR colour barely compresses (RLE saves 2%), while the flags RLE to almost nothing, and tiles make few
large chunks: that writes 3x cheaper than one RLE scanline part of the same size (docs/benchmarks.md).
Frames written as one scanline part with all four channels (before 2026-11-23 night) read the same.

`write_processed` / `read_processed` are the one writer and reader; `processed_ok` is the resume check.
Writes are atomic (temp file + rename), so a file under the final name is always complete; the check
still parses the header and the chunk table so a truncated or foreign file is not taken as done.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from lightstage.errors import LightstageError
from lightstage.exr_header import read_exr_header
from lightstage.frames import ExrPart, write_exr_parts

CHANNELS = "RGBS"
TILE = 256  # tile side of the processed frames; OpenEXR's per-chunk cost is negligible at 48 tiles per part
FLAGS_COMPRESSION = "rle"


def to_half(x: np.ndarray) -> np.ndarray:
    """float32 -> float16 with the bits of `x.astype(np.float16)` (round to nearest even), through OpenCV's
    vectorised (F16C) conversion: numpy converts element by element, ~10x slower (9 ms a 768x512 RGB frame,
    a third of the noise step). A product by 1.0 is exact; the array is passed as one 2-D channel (a scalar
    applies to channel 0 only). Other dtypes go through numpy (float64 via float32 would round twice)."""
    import cv2

    if x.dtype != np.float32 or x.size == 0:
        return x.astype(np.float16)
    flat = np.ascontiguousarray(x).reshape(x.shape[0] if x.ndim > 1 else 1, -1)
    return cv2.multiply(flat, 1.0, dtype=cv2.CV_16F).reshape(x.shape)


def to_float(x: np.ndarray) -> np.ndarray:
    """float16 -> float32 (exact) through PyTorch's vectorised conversion."""
    import torch

    return torch.from_numpy(np.ascontiguousarray(x)).float().numpy()


class HalfRounder:
    """Rounds (h, w, 3) float32 processed frames to the stored half precision, reusing its buffers.

    `__call__` returns the R, G, B half planes the writer stores and rounds the float32 frame in place, so the
    statistics see exactly the stored values (as a resumed run that reads the frame back does). The conversion
    runs on the interleaved frame (PyTorch's vectorised half conversion, both ways) and OpenCV splits the half
    bits into planes: 2.5x cheaper than converting through a transposed view. Reusing the buffers per chunk
    avoids page-faulting fresh memory for every frame.
    """

    def __init__(self, height: int, width: int) -> None:
        import torch

        self._half = torch.empty((height, width, 3), dtype=torch.float16)
        self._planes = np.empty((3, height, width), np.float16)

    def __call__(self, rgb: np.ndarray) -> np.ndarray:
        """(3, h, w) float16 planes of `rgb` (valid until the next call); `rgb` is rounded in place."""
        import cv2
        import torch

        t = torch.from_numpy(rgb)
        if tuple(t.shape) != tuple(self._half.shape) or t.dtype != torch.float32:
            raise LightstageError(
                f"frame {t.dtype} {tuple(t.shape)} does not fit a {tuple(self._half.shape)} buffer"
            )
        self._half.copy_(t)  # round to nearest even
        t.copy_(self._half)  # exact: the stored values, back in float32
        bits = self._half.numpy().view(np.uint16)  # OpenCV has no half type; a split moves bits only
        cv2.split(bits, [plane.view(np.uint16) for plane in self._planes])
        return self._planes


def write_processed(
    path: str | os.PathLike[str],
    rgb_planes: np.ndarray,
    saturated: np.ndarray,
    compression: str,
    attributes: dict[str, str | float | int] | None = None,
) -> None:
    """Write a processed frame atomically from (3, h, w) half R, G, B planes (see `HalfRounder`) and (h, w)
    bool saturation flags; `compression` is the stage config's (its default lives there)."""
    rgb_planes = np.asarray(rgb_planes)
    if rgb_planes.ndim != 3 or rgb_planes.shape[0] != 3 or rgb_planes.shape[1:] != saturated.shape:
        raise LightstageError(
            f"{path}: expected (3, h, w) RGB planes and (h, w) flags, got {rgb_planes.shape} and {saturated.shape}"
        )
    planes = {c: np.ascontiguousarray(rgb_planes[i], dtype=np.float16) for i, c in enumerate("RGB")}
    parts = [
        ExrPart("rgb", planes, compression),
        ExrPart("saturation", {"S": _flags_to_half(saturated)}, FLAGS_COMPRESSION),
    ]
    write_exr_parts(path, parts, tile=TILE, attributes=attributes)


def read_processed(
    path: str | os.PathLike[str], expected_size: tuple[int, int] | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Read a processed frame: ((h, w, 3) float32 linear RGB, (h, w) bool saturated)."""
    rgb, sat = read_processed_half(path, expected_size)
    return to_float(rgb), sat


def read_processed_half(
    path: str | os.PathLike[str], expected_size: tuple[int, int] | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Like read_processed, with RGB left as stored (float16)."""
    import OpenEXR

    path = Path(path)
    header = read_exr_header(path)
    _check(header, expected_size)
    try:
        f = OpenEXR.File(str(path), separate_channels=True)
        ch = {name: c for part in f.parts for name, c in part.channels.items()}
        rgb = np.stack([ch[c].pixels for c in "RGB"], axis=-1)
        sat = ch["S"].pixels > 0.5
    except Exception as e:  # noqa: BLE001 - decoder failures become one clear message
        raise LightstageError(f"{path}: corrupt processed frame ({str(e).strip()[:200]})") from None
    if sat.shape != rgb.shape[:2]:
        raise LightstageError(f"{path}: saturation flags are {sat.shape}, the colour planes {rgb.shape[:2]}")
    if rgb.dtype != np.float16:
        rgb = rgb.astype(np.float16)
    return rgb, sat


def processed_ok(path: str | os.PathLike[str], expected_size: tuple[int, int]) -> bool:
    """True when `path` is a complete processed frame of the expected (width, height)."""
    path = Path(path)
    if not path.is_file():
        return False
    try:
        _check(read_exr_header(path), expected_size)
    except LightstageError:
        return False
    return True


def _check(header, expected_size: tuple[int, int] | None) -> None:  # noqa: ANN001 - FrameHeader
    problem = getattr(header, "chunk_problem", None)
    if problem:
        raise LightstageError(f"{header.path}: {problem}")
    if expected_size is not None and (header.width, header.height) != tuple(expected_size):
        raise LightstageError(
            f"{header.path}: processed frame is {header.width}x{header.height}, "
            f"expected {expected_size[0]}x{expected_size[1]}"
        )
    present = {name for part in header.part_channels for name in part}
    missing = [c for c in CHANNELS if c not in present]
    if missing:
        raise LightstageError(f"{header.path}: processed frame lacks channel(s) {', '.join(missing)}")


def _flags_to_half(flags: np.ndarray) -> np.ndarray:
    """bool -> float16 0/1 by the bit pattern of 1.0 (0x3C00): an integer multiply, 15x faster than astype."""
    out = np.empty(flags.shape, np.int16)
    np.multiply(np.ascontiguousarray(flags, bool).view(np.uint8), np.int16(0x3C00), out=out, casting="unsafe")
    return out.view(np.float16)


# ---- per-view label images (WORK/preprocess/views/<g>/<c>/mask.png, zones.png) --------------------------
def read_label_png(path: str | os.PathLike[str]) -> np.ndarray:
    """A single-channel 8-bit PNG (mask or zone map) as uint8 (H, W), exact values (OpenCV, no rescaling)."""
    import cv2

    path = Path(path)
    if not path.is_file():
        raise LightstageError(f"{path}: missing (run `lightstage preprocess`)")
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise LightstageError(f"{path}: unreadable PNG")
    if img.ndim == 3:
        img = img[..., 0]
    if img.dtype != np.uint8:
        img = np.clip(img, 0, 255).astype(np.uint8)
    return img


def read_mask(path: str | os.PathLike[str]) -> np.ndarray:
    """A foreground mask PNG as bool (H, W): 0/255 and 0/1 PNGs are both accepted."""
    m = read_label_png(path)
    return m > (127 if m.max() > 1 else 0)


def read_flare_mask(path: str | os.PathLike[str], shape: tuple[int, int]) -> np.ndarray:
    """A frame's flare and bulb mask (WorkDir.flare_mask) as bool (h, w): all False when the file is absent
    (nothing of the frame is flagged)."""
    path = Path(path)
    if not path.is_file():
        return np.zeros(shape, bool)
    m = read_mask(path)
    if m.shape != tuple(shape):
        raise LightstageError(
            f"{path}: flare mask is {m.shape[1]}x{m.shape[0]}, the frame {shape[1]}x{shape[0]} "
            "(rerun `lightstage preprocess`)"
        )
    return m


def read_zones(path: str | os.PathLike[str]) -> np.ndarray:
    """A zone map PNG as labels ZONE_BACKGROUND / ZONE_BAND / ZONE_FOREGROUND (raw labels or 0/128/255)."""
    from lightstage.workdir import ZONE_BACKGROUND, ZONE_BAND, ZONE_FOREGROUND

    z = read_label_png(path)
    if z.max() <= 2:
        return z
    return np.where(z < 64, ZONE_BACKGROUND, np.where(z < 192, ZONE_BAND, ZONE_FOREGROUND)).astype(np.uint8)
