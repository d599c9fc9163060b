"""What the trainer and evaluation consume: a `BatchSource` (resumable stream of ray batches in world
coordinates) and `TestImage` records (camera, light direction, HDR target)."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Protocol

import torch


class BatchSource(Protocol):
    """A stream of batch dicts with BATCH_KEYS that can restart at any position (batches already consumed)."""

    def batches(
        self, start: int = 0, rank: int = 0, world_size: int = 1
    ) -> Iterator[dict[str, torch.Tensor]]: ...
