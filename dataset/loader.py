"""Streaming loader of ray shards for the trainer: a torch IterableDataset that reads shards sequentially through
memory maps (bounded memory: one shard mapped per process), composes every batch 1/2 foreground, 3/8 band,
1/8 background from contiguous slices of the shard's zone blocks, splits batches across DDP ranks and DataLoader
workers without duplication, and resumes at (epoch, position).

Batch dict (what the trainer consumes): origins, directions, light_positions, light_directions (B, 3) float32,
rgb (B, 3) float32 (HDR, linear), saturated (B,) bool, zone (B,) uint8 (ZONE_* labels of lightstage.workdir),
flare (B,) bool (flag bits of the ray: lightstage.records.shards). With `rays=False` it yields the compact
records instead ({"records": int16 (B, 8)}, 16 bytes a ray) and the consumer computes the rays on its own device (`RayShardDataset.table(device).expand`, as the trainer does).
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch.utils.data import DataLoader, IterableDataset, get_worker_info

from lightstage.dataset.ray_table import RayTable
from lightstage.errors import LightstageError
from lightstage.npyio import load_npy
from lightstage.records.shards import (
    COMPOSITION,
    RAY_DTYPE,
    ZONE_NAMES,
    ZONES,
    check_file,
    check_size,
    load_manifest,
)

VERIFY_MODES = ("open", "all", "never")


def _dist_rank_world() -> tuple[int, int]:
    if torch.distributed.is_available() and torch.distributed.is_initialized():
        return torch.distributed.get_rank(), torch.distributed.get_world_size()
    return 0, 1


class RayShardDataset(IterableDataset):
    """Batches of rays from WORK/shards (see module docstring). One epoch = every whole batch of every shard once
    (shards in a seeded per-epoch order, each zone block read from a seeded per-epoch rotation); global batch k
    goes to rank k mod world_size, and a rank's m-th batch to DataLoader worker m mod num_workers."""

    def __init__(
        self,
        shards_dir: str | os.PathLike[str],
        batch_size: int = 8192,
        *,
        shuffle: bool = True,
        seed: int = 0,
        rank: int | None = None,
        world_size: int | None = None,
        verify: str = "open",
        normalize: bool = False,
        rays: bool = True,
    ) -> None:
        self.root = Path(shards_dir)
        self.manifest = load_manifest(self.root)
        if batch_size < 8 or batch_size % 8:
            raise LightstageError(
                f"batch_size must be a positive multiple of 8 (1/2, 3/8, 1/8), got {batch_size}"
            )
        if verify not in VERIFY_MODES:
            raise LightstageError(f"verify: one of {', '.join(VERIFY_MODES)}, got {verify!r}")
        r, w = _dist_rank_world()
        self.rank = r if rank is None else int(rank)
        self.world_size = w if world_size is None else int(world_size)
        if not 0 <= self.rank < self.world_size:
            raise LightstageError(f"rank {self.rank} outside world size {self.world_size}")
        self.batch_size = batch_size
        self.per_zone = tuple(batch_size // 8 * c for c in COMPOSITION)
        self.shuffle, self.seed, self.verify, self.normalize = shuffle, seed, verify, normalize
        self.rays = rays
        self._table: RayTable | None = None
        self.shards = self.manifest["shards"]
        self.zone_counts = np.array(
            [[s["zones"][ZONE_NAMES[z]] for z in ZONES] for s in self.shards], np.int64
        )
        self.batches_per_shard = np.min(self.zone_counts // np.array(self.per_zone), axis=1)
        self.total_batches = int(self.batches_per_shard.sum())
        if self.total_batches // self.world_size == 0:
            raise LightstageError(
                f"{self.root}: {self.total_batches} batches of {batch_size} rays cannot feed {self.world_size} ranks"
            )
        norm = self.manifest["normalization"]
        self.normalization = {"centre": list(norm["centre"]), "scale": float(norm["scale"])}
        self.epoch = 0
        self.position = 0
        self._verified: set[int] = set()
        if verify != "never":  # every shard's size before any is read: none is ever read as fewer rays
            for rec in self.shards:
                check_size(self.root, rec)
        if verify == "all":
            for i, rec in enumerate(self.shards):
                check_file(self.root, rec)
                self._verified.add(i)

    # ---- bookkeeping -----------------------------------------------------------------------------------
    def __len__(self) -> int:
        """Batches per epoch for this rank (every rank gets the same number)."""
        return self.total_batches // self.world_size

    def set_epoch(self, epoch: int) -> None:
        self.epoch, self.position = int(epoch), 0

    def state_dict(self) -> dict[str, Any]:
        return {
            "epoch": self.epoch,
            "position": self.position,
            "seed": self.seed,
            "batch_size": self.batch_size,
            "world_size": self.world_size,
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        for key in ("seed", "batch_size", "world_size"):
            if key in state and state[key] != getattr(self, key):
                raise LightstageError(
                    f"loader state: {key} was {state[key]}, this loader has {getattr(self, key)}"
                )
        position = int(state["position"])
        if not 0 <= position <= len(self):
            raise LightstageError(
                f"loader state: position {position} outside the epoch ({len(self)} batches)"
            )
        self.epoch, self.position = int(state["epoch"]), position

    # ---- the epoch plan --------------------------------------------------------------------------------
    def _plan(self, epoch: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(shard order, cumulative batch ends in that order, per-shard per-zone rotation offsets)."""
        n = len(self.shards)
        rng = np.random.default_rng([self.seed, epoch])
        order = rng.permutation(n) if self.shuffle else np.arange(n)
        ends = np.cumsum(self.batches_per_shard[order])
        if self.shuffle:
            offsets = (rng.random((n, len(ZONES))) * self.zone_counts).astype(np.int64)
        else:
            offsets = np.zeros((n, len(ZONES)), np.int64)
        return order, ends, offsets

    def global_indices(self, epoch: int, start: int, worker: int = 0, num_workers: int = 1) -> range:
        """Global batch indices this (rank, worker) produces in `epoch` from rank-local position `start`."""
        per_rank = len(self)
        return range(
            (start + worker) * self.world_size + self.rank,
            per_rank * self.world_size,
            num_workers * self.world_size,
        )

    def _open(self, shard: int) -> np.ndarray:
        rec = self.shards[shard]
        path = self.root / rec["file"]
        if self.verify == "open" and shard not in self._verified:
            check_file(self.root, rec)
            self._verified.add(shard)
        try:
            arr = load_npy(path, mmap_mode="r")
        except (OSError, ValueError) as e:
            raise LightstageError(f"{path}: unreadable shard ({e})") from None
        if arr.dtype != RAY_DTYPE or arr.shape != (rec["rays"],):
            raise LightstageError(
                f"{path}: shard holds {arr.shape} of {arr.dtype}, manifest says {rec['rays']} rays"
            )
        return arr

    def _read(self, data: np.ndarray, shard: int, j: int, offsets: np.ndarray) -> np.ndarray:
        """Batch j of a shard: per zone a (rotated, wrapping) contiguous slice of the zone block."""
        counts = self.zone_counts[shard]
        out = np.empty(self.batch_size, RAY_DTYPE)
        o = 0
        block = 0
        for zi, b in enumerate(self.per_zone):
            n = int(counts[zi])
            a = (int(offsets[zi]) + j * b) % n
            first = min(b, n - a)
            out[o : o + first] = data[block + a : block + a + first]
            if first < b:
                out[o + first : o + b] = data[block : block + b - first]
            o += b
            block += n
        return out

    def table(self, device: torch.device | str = "cpu") -> RayTable:
        """The manifest's cameras and lights on `device`, to compute the rays of compact records there."""
        return RayTable(self.manifest, device)

    def compact(self, rec: np.ndarray) -> dict[str, torch.Tensor]:
        """Structured rays -> {"records": int16 (B, 8)}: their 16 bytes each, one tensor (one shared-memory
        segment when a DataLoader worker hands the batch over)."""
        return {"records": torch.from_numpy(rec.view(np.int16).reshape(len(rec), RAY_DTYPE.itemsize // 2))}

    def to_tensors(self, rec: np.ndarray) -> dict[str, torch.Tensor]:
        """Structured rays -> the batch dict of float32 / bool / uint8 tensors (rays computed on the CPU)."""
        if self._table is None:
            self._table = self.table("cpu")
        return self._table.expand(
            self.compact(rec)["records"], self.normalization if self.normalize else None
        )

    def iter_records(
        self, epoch: int, start: int = 0, worker: int = 0, num_workers: int = 1
    ) -> Iterator[tuple[int, np.ndarray]]:
        """(global batch index, structured rays) for this rank/worker in `epoch` from position `start`."""
        order, ends, offsets = self._plan(epoch)
        cur_shard, data = -1, None
        for k in self.global_indices(epoch, start, worker, num_workers):
            pos = int(np.searchsorted(ends, k, side="right"))
            shard = int(order[pos])
            j = k - (int(ends[pos - 1]) if pos else 0)
            if shard != cur_shard:
                data = None  # unmap the previous shard before mapping the next: one shard mapped at a time
                data = self._open(shard)
                cur_shard = shard
            yield k, self._read(data, shard, j, offsets[shard])

    def __iter__(self) -> Iterator[dict[str, torch.Tensor]]:
        info = get_worker_info()
        worker, num_workers = (info.id, info.num_workers) if info is not None else (0, 1)
        epoch, start = self.epoch, self.position
        for _, rec in self.iter_records(epoch, start, worker, num_workers):
            if info is None:
                self.position += 1
            yield self.to_tensors(rec) if self.rays else self.compact(rec)
        if info is None:
            self.set_epoch(epoch + 1)

    def batches(
        self, start: int = 0, rank: int | None = None, world_size: int | None = None
    ) -> Iterator[dict[str, torch.Tensor]]:
        """An endless stream over epochs starting after `start` batches already consumed by this rank
        (rank/world_size, when given, must match the dataset's)."""
        if (rank is not None and rank != self.rank) or (
            world_size is not None and world_size != self.world_size
        ):
            raise LightstageError(
                f"batches(rank={rank}, world_size={world_size}) differs from the dataset's "
                f"({self.rank}, {self.world_size}); construct the dataset with them"
            )
        per = len(self)
        self.epoch, self.position = divmod(int(start), per)
        while True:
            yield from self


class RayLoader:
    """A DataLoader over a RayShardDataset (batch_size=None: the dataset batches) that counts what it yields, so
    state_dict() / load_state_dict() resume exactly, also with worker processes."""

    def __init__(
        self,
        dataset: RayShardDataset,
        num_workers: int = 0,
        pin_memory: bool = False,
        prefetch_factor: int | None = None,
    ) -> None:
        self.dataset = dataset
        self.num_workers = num_workers
        kw: dict[str, Any] = {"batch_size": None, "num_workers": num_workers, "pin_memory": pin_memory}
        if num_workers > 0 and prefetch_factor:
            kw["prefetch_factor"] = prefetch_factor
        self._kw = kw

    def __len__(self) -> int:
        return len(self.dataset)

    def state_dict(self) -> dict[str, Any]:
        return self.dataset.state_dict()

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.dataset.load_state_dict(state)

    def __iter__(self) -> Iterator[dict[str, torch.Tensor]]:
        ds = self.dataset
        epoch = ds.epoch
        if self.num_workers == 0:
            yield from ds
            return
        for batch in DataLoader(ds, **self._kw):
            ds.position += 1
            yield batch
        ds.set_epoch(epoch + 1)
