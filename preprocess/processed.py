"""The processed frame on disk (WorkDir.frame): half EXR with channels R, G, B and S (1 = saturated source).

`write_processed` / `read_processed` are the one writer and reader; `processed_ok` is the resume check.
Writes are atomic (temp file + rename), so a file under the final name is always complete; the check
still parses the header and the chunk table so a truncated or foreign file is not taken as done.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from lightstage.capture.frames import read_exr_header, write_exr
from lightstage.errors import LightstageError

CHANNELS = "RGBS"
# Lossless EXR compressions for processed frames. ZIP is the smallest; RLE writes ~5x faster (+30% size).
COMPRESSIONS = ("zip", "piz", "rle", "none")


def to_half(x: np.ndarray) -> np.ndarray:
    """float32 -> float16 (round to nearest even) through PyTorch's vectorised conversion."""
    import torch

    return torch.from_numpy(np.ascontiguousarray(x, dtype=np.float32)).half().numpy()


def to_float(x: np.ndarray) -> np.ndarray:
    """float16 -> float32 (exact) through PyTorch's vectorised conversion."""
    import torch

    return torch.from_numpy(np.ascontiguousarray(x)).float().numpy()


def pack(rgb_half: np.ndarray, saturated: np.ndarray) -> np.ndarray:
    """(h, w, 4) half image R, G, B, S from half RGB and bool flags."""
    out = np.empty((*rgb_half.shape[:2], 4), np.float16)
    out[..., :3] = rgb_half
    out[..., 3] = saturated
    return out


def write_processed(
    path: str | os.PathLike[str],
    rgb_half: np.ndarray,
    saturated: np.ndarray,
    compression: str = "zip",
    attributes: dict[str, str | float | int] | None = None,
) -> None:
    """Write a processed frame atomically (RGB already rounded to half by the caller)."""
    if compression != "rle":
        write_exr(
            path, pack(rgb_half, saturated), compression=compression, channels=CHANNELS, attributes=attributes
        )
        return
    import OpenEXR

    from lightstage.atomic import atomic_path

    planes = {c: np.ascontiguousarray(rgb_half[..., i], dtype=np.float16) for i, c in enumerate("RGB")}
    planes["S"] = saturated.astype(np.float16)
    header: dict = {"compression": OpenEXR.RLE_COMPRESSION, "type": OpenEXR.scanlineimage}
    for k, v in (attributes or {}).items():
        header[k] = v if isinstance(v, str) else float(v)
    with atomic_path(path) as tmp:
        try:
            OpenEXR.File(header, planes).write(str(tmp))
        except Exception as e:  # noqa: BLE001 - one clear message naming the file
            raise LightstageError(f"{path}: cannot write EXR ({str(e).strip()[:200]})") from None


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
        ch = f.parts[0].channels
        rgb = np.stack([ch[c].pixels for c in "RGB"], axis=-1)
        sat = ch["S"].pixels > 0.5
    except Exception as e:  # noqa: BLE001 - decoder failures become one clear message
        raise LightstageError(f"{path}: corrupt processed frame ({str(e).strip()[:200]})") from None
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
    missing = [c for c in CHANNELS if c not in header.channels]
    if missing:
        raise LightstageError(f"{header.path}: processed frame lacks channel(s) {', '.join(missing)}")
