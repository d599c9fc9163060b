"""What the trainer and evaluation consume, and the adapters from the dataset stage's outputs (WORK/shards) to what the trainer and evaluation consume:
`ShardSource` (a BatchSource over lightstage.dataset.loader) and the test images in WORK/shards/test."""

from __future__ import annotations

import itertools
from collections.abc import Iterator
from typing import Protocol

import torch

from lightstage.errors import LightstageError
from lightstage.records.shards import TestImage, check_file, read_test_image, read_test_index
from lightstage.workdir import WorkDir


class BatchSource(Protocol):
    """A stream of batch dicts with BATCH_KEYS that can restart at any position (batches already consumed)."""

    def batches(
        self, start: int = 0, rank: int = 0, world_size: int = 1
    ) -> Iterator[dict[str, torch.Tensor]]: ...


class ShardSource:
    """The streaming shard loader as a BatchSource: `batches(start, rank, world)` resumes after `start` batches
    this rank already consumed (the loader position saved in checkpoints). The loader hands over compact records
    (16 bytes a ray); their rays are computed on `device`, the one that trains (lightstage.dataset.ray_table)."""

    def __init__(
        self,
        work: WorkDir,
        batch_size: int,
        seed: int = 0,
        workers: int = 0,
        device: torch.device | str = "cpu",
    ):
        self.work, self.seed, self.workers, self.device = work, seed, workers, torch.device(device)
        self.batch_size = max(8, batch_size // 8 * 8)
        manifest = work.shards_dir / "manifest.json"
        if not manifest.is_file():
            raise LightstageError(f"{manifest}: no training shards (run lightstage shard WORK first)")

    def dataset(self, rank: int = 0, world_size: int = 1):
        from lightstage.dataset.loader import RayShardDataset

        return RayShardDataset(
            self.work.shards_dir,
            self.batch_size,
            seed=self.seed,
            rank=rank,
            world_size=world_size,
            rays=False,
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
        table = ds.table(self.device)
        if self.workers <= 0:
            stream = ds.batches(start)
        else:
            from lightstage.dataset.loader import RayLoader

            ds.epoch, ds.position = divmod(int(start), len(ds))
            loader = RayLoader(ds, num_workers=self.workers)
            stream = itertools.chain.from_iterable(itertools.repeat(loader))  # epoch after epoch
        for compact in stream:
            yield table.expand(compact["records"])


def iter_test_images(work: WorkDir) -> Iterator[TestImage]:
    """The test split's images in index order."""
    for rec in read_test_index(work.shards_dir):
        yield read_test_image(check_file(work.shards_dir, rec))


def count_test_images(work: WorkDir) -> int:
    """Number of test images listed in WORK/shards/test/index.json (0 when absent)."""
    return len(read_test_index(work.shards_dir))
