"""The shard format the dataset stage writes and training reads: the packed ray dtype, the manifest, the batch
keys, and the test images (shards/test/*.npz with shards/test/index.json). One definition, both sides.

Batch dict (what the trainer consumes, `BATCH_KEYS`): origins, directions, light_positions, light_directions
(B, 3) float32, rgb (B, 3) float32 (HDR, linear), saturated (B,) bool, zone (B,) uint8 (ZONE_* of lightstage.workdir),
flare (B,) bool (the pixel is in its frame's flare and bulb mask: no photometric loss).

A ray's 16-bit `flags` hold the saturated bit, the zone and the flare bit (the target is a pixel of the frame's
flare and bulb mask, preprocess/flare.py): `pack_flags` and `flags_*` below.
"""

from __future__ import annotations

import hashlib
import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from lightstage.atomic import write_json_atomic
from lightstage.cameras import PinholeCamera
from lightstage.errors import LightstageError
from lightstage.ids import FrameId
from lightstage.npyio import load_npz
from lightstage.workdir import ZONE_BACKGROUND, ZONE_BAND, ZONE_FOREGROUND

SHARD_FORMAT_VERSION = 2
# One ray, 16 bytes, packed: only what cannot be recomputed. rgb = the processed half pixel (0 outside the mask
# and on the border); flags = FLAG_* bits; pixel = integer pixel (column i, row j) of the processed image, outside
# it for border rays; view / light index the manifest's `views` (and `cameras`) and the 0-based light. Origins,
# directions and the light's position and direction come from the manifest's camera and light tables where the
# rays are read (lightstage.dataset.ray_table).
RAY_DTYPE = np.dtype(
    [
        ("rgb", "<f2", (3,)),
        ("flags", "<u2"),
        ("pixel", "<i2", (2,)),
        ("view", "<u2"),
        ("light", "<u2"),
    ]
)
# flags: bit 0 saturated (the source pixel was at/above the stage cutoff), bits 1-2 the sampling zone (ZONE_*),
# bit 3 flare (the pixel lies in a detected lens flare), bits 4-15 spare (zero).
FLAG_SATURATED = 1
FLAG_ZONE_SHIFT = 1
FLAG_ZONE_MASK = 0b11 << FLAG_ZONE_SHIFT
FLAG_FLARE = 1 << 3
LEGACY_FORMATS = {1: "64-byte rays with stored origins and directions"}


def pack_flags(saturated: np.ndarray, zone: np.ndarray | int, flare: np.ndarray | None = None) -> np.ndarray:
    """uint16 flags of rays from their saturated bits, zone labels and (optional) flare bits."""
    f = np.asarray(saturated, np.uint16) & 1 | (np.asarray(zone, np.uint16) << FLAG_ZONE_SHIFT)
    if flare is not None:
        f = f | (np.asarray(flare, np.uint16) & 1) << 3
    return np.asarray(f, np.uint16)


def flags_saturated(flags: Any) -> Any:
    """The saturated bits of flags (numpy or torch) as bool."""
    return (flags & FLAG_SATURATED) != 0


def flags_zone(flags: Any) -> Any:
    """The zone labels of flags (numpy or torch) as uint8."""
    z = (flags & FLAG_ZONE_MASK) >> FLAG_ZONE_SHIFT
    return z.to(dtype=_torch_uint8()) if hasattr(z, "to") else np.asarray(z).astype(np.uint8)


def flags_flare(flags: Any) -> Any:
    """The flare bits of flags (numpy or torch) as bool."""
    return (flags & FLAG_FLARE) != 0


def _torch_uint8() -> Any:
    import torch

    return torch.uint8


# Block order inside chunks and shards, and the batch composition of the paper (1/2, 3/8, 1/8).
ZONES = (ZONE_FOREGROUND, ZONE_BAND, ZONE_BACKGROUND)
ZONE_NAMES = {ZONE_FOREGROUND: "foreground", ZONE_BAND: "band", ZONE_BACKGROUND: "background"}
COMPOSITION = (4, 3, 1)  # eighths
MANIFEST = "manifest.json"
TEST_INDEX = "test/index.json"
BATCH_KEYS = (
    "origins",
    "directions",
    "light_positions",
    "light_directions",
    "rgb",
    "saturated",
    "zone",
    "flare",
)


def rebuild_command(shards_dir: str | os.PathLike[str]) -> str:
    """The command that rebuilds the shards of WORK/shards (`lightstage shard WORK --force`)."""
    return f"lightstage shard {Path(shards_dir).resolve().parent} --force"


def file_sha256(path: str | os.PathLike[str]) -> str:
    """sha256 of a file, streamed (bounded memory)."""
    with open(path, "rb") as f:
        return hashlib.file_digest(f, "sha256").hexdigest()


def check_size(shards_dir: str | os.PathLike[str], record: dict[str, Any]) -> Path:
    """The path of a manifest record's file (shard or test image) after checking that it exists and has the
    recorded size: a missing, truncated or grown file is a LightstageError naming it and the rebuild command,
    so it is never read as fewer rays."""
    path = Path(shards_dir) / record["file"]
    if not path.is_file():
        raise LightstageError(
            f"{path}: missing (listed in {MANIFEST}); rebuild the shards: {rebuild_command(shards_dir)}"
        )
    size = path.stat().st_size
    if "bytes" in record and size != record["bytes"]:
        raise LightstageError(
            f"{path}: is {size} bytes, manifest says {record['bytes']} (truncated or replaced); "
            f"rebuild the shards: {rebuild_command(shards_dir)}"
        )
    return path


def check_file(shards_dir: str | os.PathLike[str], record: dict[str, Any]) -> Path:
    """check_size, then the sha256 against the record's (when it has one): a foreign or corrupt file of the right
    size is a LightstageError naming it and the rebuild command."""
    path = check_size(shards_dir, record)
    if "sha256" in record:
        sha = file_sha256(path)
        if sha != record["sha256"]:
            raise LightstageError(
                f"{path}: checksum mismatch (sha256 {sha[:12]}..., manifest {record['sha256'][:12]}...): the "
                f"file is corrupt or from another run; rebuild the shards: {rebuild_command(shards_dir)}"
            )
    return path


def load_manifest(shards_dir: str | os.PathLike[str]) -> dict[str, Any]:
    """Read and check shards/manifest.json (format version and ray dtype)."""
    path = Path(shards_dir) / MANIFEST
    try:
        m = json.loads(path.read_text())
    except OSError as e:
        raise LightstageError(
            f"{path}: cannot read shard manifest ({e.strerror}); run `lightstage shard`"
        ) from None
    except json.JSONDecodeError as e:
        raise LightstageError(f"{path}: invalid JSON ({e})") from None
    version = m.get("format_version")
    if version in LEGACY_FORMATS:
        raise LightstageError(
            f"{path}: shards in the old format {version} ({LEGACY_FORMATS[version]}); this lightstage reads format "
            f"{SHARD_FORMAT_VERSION} (16-byte rays): rerun `{rebuild_command(shards_dir)}`"
        )
    if version != SHARD_FORMAT_VERSION:
        raise LightstageError(
            f"{path}: unsupported shard format {version!r}; rerun `{rebuild_command(shards_dir)}`"
        )
    if m.get("dtype", {}).get("descr") != str(RAY_DTYPE.descr):
        raise LightstageError(
            f"{path}: ray dtype {m.get('dtype', {}).get('descr')} differs from this lightstage's; "
            f"rerun `{rebuild_command(shards_dir)}`"
        )
    return m


@dataclass
class TestImage:
    """One evaluation image: a pinhole camera, the unit light direction and the linear HDR target (H, W, 3);
    `mask`: (H, W) foreground (metrics score the target as 0 outside it; None: no mask, every pixel);
    `frame`: the capture frame it is (None for synthetic images), so a noise-free render can be found;
    `flare`: (H, W) the frame's flare and bulb mask (None: nothing flagged)."""

    name: str
    camera: PinholeCamera
    light_direction: np.ndarray
    target: np.ndarray
    saturated: np.ndarray | None = None
    mask: np.ndarray | None = None
    frame: FrameId | None = None
    flare: np.ndarray | None = None

    @property
    def masked_target(self) -> np.ndarray:
        """The target with 0 outside the mask (what evaluation scores against)."""
        if self.mask is None:
            return self.target
        return np.where(self.mask[..., None], self.target, 0).astype(self.target.dtype)


def write_test_index(shards_dir: str | os.PathLike[str], images: list[dict[str, Any]]) -> None:
    """shards/test/index.json: the test images in order, each {file, group, camera, light} (atomic)."""
    write_json_atomic(Path(shards_dir) / TEST_INDEX, {"images": images})


def read_test_index(shards_dir: str | os.PathLike[str]) -> list[dict[str, Any]]:
    """The records of shards/test/index.json (file, group, camera, light), [] when absent."""
    index = Path(shards_dir) / TEST_INDEX
    if not index.is_file():
        return []
    try:
        return list(json.loads(index.read_text())["images"])
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise LightstageError(f"{index}: unreadable test index ({e})") from e


def read_test_image(path: Path) -> TestImage:
    """One shards/test/*.npz (rgb, saturated, K, R, t, dist, width, height, light_direction; mask, flare and the
    frame's group/camera/light when written) as a TestImage."""
    try:
        z = load_npz(path)
        mask = np.array(z["mask"], bool) if "mask" in z else None
        frame = (
            FrameId(str(z["group"]), str(z["camera"]), int(z["light"]))
            if {"group", "camera", "light"} <= z.keys()
            else None
        )
        cam = PinholeCamera(
            np.array(z["K"], np.float64),
            np.array(z["R"], np.float64),
            np.array(z["t"], np.float64).reshape(3),
            int(z["width"]),
            int(z["height"]),
            np.array(z["dist"], np.float64).reshape(-1),
        )
        return TestImage(
            path.stem,
            cam,
            np.array(z["light_direction"], np.float64).reshape(3),
            np.array(z["rgb"], np.float32),
            np.array(z["saturated"], bool),
            mask,
            frame,
            np.array(z["flare"], bool) if "flare" in z else None,
        )
    except (OSError, ValueError, KeyError) as e:
        raise LightstageError(f"{path}: unreadable test image ({e})") from e
