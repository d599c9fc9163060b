"""The shard format the dataset stage writes and training reads: the packed ray dtype, the manifest, the batch
keys, and the test images (shards/test/*.npz with shards/test/index.json). One definition, both sides.

Batch dict (what the trainer consumes, `BATCH_KEYS`): origins, directions, light_positions, light_directions
(B, 3) float32, rgb (B, 3) float32 (HDR, linear), saturated (B,) bool, zone (B,) uint8 (ZONE_* of lightstage.workdir),
flare (B,) bool (the pixel is in its frame's flare and bulb mask: no photometric loss).

A ray's `saturated` byte holds flag bits: FLAG_SATURATED (the source clipped) and FLAG_FLARE (the target is a pixel
of the frame's flare and bulb mask, preprocess/flare.py).
"""

from __future__ import annotations

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

SHARD_FORMAT_VERSION = 1
# One ray, 64 bytes, packed. pixel = integer pixel (column i, row j) of the processed image, outside it for
# border rays; view / light index the manifest's `views` list and the 0-based light.
RAY_DTYPE = np.dtype(
    [
        ("origin", "<f4", (3,)),
        ("direction", "<f4", (3,)),
        ("light_position", "<f4", (3,)),
        ("light_direction", "<f4", (3,)),
        ("rgb", "<f2", (3,)),
        ("saturated", "u1"),
        ("zone", "u1"),
        ("view", "<u2"),
        ("light", "<u2"),
        ("pixel", "<i2", (2,)),
    ]
)
# Block order inside chunks and shards, and the batch composition of the paper (1/2, 3/8, 1/8).
ZONES = (ZONE_FOREGROUND, ZONE_BAND, ZONE_BACKGROUND)
ZONE_NAMES = {ZONE_FOREGROUND: "foreground", ZONE_BAND: "band", ZONE_BACKGROUND: "background"}
COMPOSITION = (4, 3, 1)  # eighths
FLAG_SATURATED = 1
FLAG_FLARE = 2
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
    if m.get("format_version") != SHARD_FORMAT_VERSION:
        raise LightstageError(f"{path}: unsupported shard format {m.get('format_version')!r}")
    if m.get("dtype", {}).get("descr") != str(RAY_DTYPE.descr):
        raise LightstageError(
            f"{path}: ray dtype {m.get('dtype', {}).get('descr')} differs from this lightstage's"
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
