"""Settings of the shard stage (`shard:` in the pipeline config, `lightstage shard` flags)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from lightstage.config import load, require, require_choice


@dataclass(frozen=True)
class ShardConfig:
    """Rays per training image, rays per shard, the sampling zones, the padded border (pad the short image side
    to a square, plus `border_px` all round; those rays have target 0), background target ('zero' as the paper:
    every pixel outside the mask has target 0; 'pixel': keep values), seed, local processes.

    Rays per image (`rays_per_image` 0, the default) follow the data: `foreground_fraction` of the image's
    foreground pixels, drawn without repetition (1.0: every foreground pixel of every training frame once per
    epoch, as the paper's code streams them), plus 3/4 as many band and 1/4 as many background rays (the
    paper's 1/2 : 3/8 : 1/8). The band is the outer ring of the mask `band_fraction` of the image width wide
    (the paper's code: 200 px at 2048 x 1366). `rays_per_image` > 0 draws that fixed count per image in 4:3:1."""

    rays_per_image: int = 0  # 0: in proportion to the image's foreground (foreground_fraction)
    foreground_fraction: float = 1.0
    band_fraction: float = 200 / 2048
    rays_per_shard: int = 1 << 20
    pad_to_square: bool = True
    border_px: int = 16
    background_target: str = "zero"
    seed: int = 0
    workers: int = 0  # 0: min(cpu count, 4); 1: in this process
    compress_test: bool = True
    force: bool = False

    def __post_init__(self) -> None:
        require(
            0 < self.foreground_fraction <= 1,
            "foreground_fraction",
            f"must be in (0, 1], got {self.foreground_fraction}",
        )
        require(0 <= self.band_fraction <= 1, "band_fraction", f"must be in [0, 1], got {self.band_fraction}")
        for k in ("rays_per_image", "rays_per_shard"):
            v = getattr(self, k)
            ok = (k == "rays_per_image" and v == 0) or (v >= 8 and v % 8 == 0)
            require(ok, k, f"must be a positive multiple of 8, got {v}")
        require_choice(self.background_target, "background_target", ("zero", "pixel"))
        require(self.border_px >= 0, "border_px", f"must be >= 0, got {self.border_px}")
        require(self.workers >= 0, "workers", f"must be >= 0, got {self.workers}")

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> ShardConfig:
        """The strict loader (`lightstage.config`): unknown keys, wrong types and bad values name the key."""
        return load(cls, d)
