"""Adapters from the dataset stage's outputs (WORK/shards) to what the trainer and evaluation consume:
`ShardSource` (a BatchSource over lightstage.dataset.loader) and the test images in WORK/shards/test."""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import torch

from lightstage.cameras import PinholeCamera
from lightstage.capture.layout import FrameId
from lightstage.errors import LightstageError
from lightstage.training.data import TestImage
from lightstage.workdir import WorkDir


class ShardSource:
    """The streaming shard loader as a BatchSource: `batches(start, rank, world)` resumes after `start` batches
    this rank already consumed (the loader position saved in checkpoints)."""

    def __init__(self, work: WorkDir, batch_size: int, seed: int = 0, workers: int = 0):
        self.work, self.seed, self.workers = work, seed, workers
        self.batch_size = max(8, batch_size // 8 * 8)
        manifest = work.shards_dir / "manifest.json"
        if not manifest.is_file():
            raise LightstageError(f"{manifest}: no training shards (run lightstage shard WORK first)")

    def dataset(self, rank: int = 0, world_size: int = 1):
        from lightstage.dataset.loader import RayShardDataset

        return RayShardDataset(
            self.work.shards_dir, self.batch_size, seed=self.seed, rank=rank, world_size=world_size
        )

    def normalization(self) -> dict:
        """The scene frame the shards were written with: centre, scale, box ([box_min, box_max] in world metres
        or None: samples then fill the unit cube) and hull (bool voxels tiling the box, or None)."""
        from lightstage.dataset.bounds import decode_hull

        norm = self.dataset().manifest["normalization"]
        return {
            "centre": list(norm["centre"]),
            "scale": float(norm["scale"]),
            "box": [list(norm["box_min"]), list(norm["box_max"])] if "box_min" in norm else None,
            "hull": torch.from_numpy(decode_hull(norm["hull"])) if "hull" in norm else None,
        }

    def batches(
        self, start: int = 0, rank: int = 0, world_size: int = 1
    ) -> Iterator[dict[str, torch.Tensor]]:
        ds = self.dataset(rank, world_size)
        if self.workers <= 0:
            yield from ds.batches(start)
            return
        from lightstage.dataset.loader import RayLoader

        ds.epoch, ds.position = divmod(int(start), len(ds))
        loader = RayLoader(ds, num_workers=self.workers)
        while True:
            yield from loader


def _test_index(work: WorkDir) -> list[dict]:
    index = work.shards_dir / "test" / "index.json"
    if not index.is_file():
        return []
    try:
        return list(json.loads(index.read_text())["images"])
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise LightstageError(f"{index}: unreadable test index ({e})") from e


def count_test_images(work: WorkDir) -> int:
    """Number of test images listed in WORK/shards/test/index.json (0 when absent)."""
    return len(_test_index(work))


def read_test_image(path: Path) -> TestImage:
    """One shards/test/*.npz (rgb, saturated, K, R, t, dist, width, height, light_direction; mask and the
    frame's group/camera/light when written) as a TestImage."""
    try:
        with np.load(path) as z:
            mask = np.array(z["mask"], bool) if "mask" in z.files else None
            frame = (
                FrameId(str(z["group"]), str(z["camera"]), int(z["light"]))
                if {"group", "camera", "light"} <= set(z.files)
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
            )
    except (OSError, ValueError, KeyError) as e:
        raise LightstageError(f"{path}: unreadable test image ({e})") from e


def iter_test_images(work: WorkDir) -> Iterator[TestImage]:
    """The test split's images in index order."""
    for rec in _test_index(work):
        yield read_test_image(work.shards_dir / rec["file"])
