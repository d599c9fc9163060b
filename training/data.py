"""What the trainer and evaluation consume: a `BatchSource` (resumable stream of ray batches in world
coordinates) and `TestImage` records (camera, light direction, HDR target)."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from typing import Protocol

import numpy as np
import torch

from lightstage.cameras import PinholeCamera
from lightstage.capture.layout import FrameId

BATCH_KEYS = ("origins", "directions", "light_positions", "light_directions", "rgb", "saturated", "zone")


class BatchSource(Protocol):
    """A stream of batch dicts with BATCH_KEYS that can restart at any position (batches already consumed)."""

    def batches(
        self, start: int = 0, rank: int = 0, world_size: int = 1
    ) -> Iterator[dict[str, torch.Tensor]]: ...


@dataclass
class TestImage:
    """One evaluation image: a pinhole camera, the unit light direction and the linear HDR target (H, W, 3);
    `mask`: (H, W) foreground (metrics score the target as 0 outside it; None: no mask, every pixel);
    `frame`: the capture frame it is (None for synthetic images), so a noise-free render can be found."""

    name: str
    camera: PinholeCamera
    light_direction: np.ndarray
    target: np.ndarray
    saturated: np.ndarray | None = None
    mask: np.ndarray | None = None
    frame: FrameId | None = None

    @property
    def masked_target(self) -> np.ndarray:
        """The target with 0 outside the mask (what evaluation scores against)."""
        if self.mask is None:
            return self.target
        return np.where(self.mask[..., None], self.target, 0).astype(self.target.dtype)
