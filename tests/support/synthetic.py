"""An analytic training problem for tests, benchmarks and examples: a Lambertian-like sphere under random
directional lights, seen by rays from random directions, batched like the shard loader (1/2 foreground,
3/8 near-silhouette band, 1/8 background) and reproducible per (seed, rank, step)."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, field

import numpy as np
import torch

from lightstage.cameras import PinholeCamera, look_at, pixel_centers, pixel_rays
from lightstage.records.shards import TestImage
from lightstage.workdir import ZONE_BACKGROUND, ZONE_BAND, ZONE_FOREGROUND


@dataclass
class SyntheticSphere:
    """Sphere of `radius` at `centre` (world metres) with colour `albedo * (ambient + max(0, n . light))`."""

    batch_size: int = 512
    seed: int = 0
    centre: tuple[float, float, float] = (0.1, -0.2, 0.3)
    radius: float = 0.5
    scale: float = 0.8  # bounds scale: the sphere fills [-0.625, 0.625]^3 of the unit cube
    albedo: tuple[float, float, float] = (0.8, 0.5, 0.3)
    ambient: float = 0.1
    camera_distance: float = 2.5
    band: float = 0.15  # rays passing within radius * (1 + band) of the centre but missing are "band"
    zone_fractions: tuple[float, float, float] = field(default=(0.5, 0.375, 0.125))

    def shade(
        self, origins: np.ndarray, directions: np.ndarray, light: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """(rgb (N, 3), zone (N,)) of world rays against the sphere under unit light directions (N, 3)."""
        c = np.asarray(self.centre)
        oc = origins - c
        b = np.sum(oc * directions, -1)
        closest = np.sqrt(np.maximum(np.sum(oc * oc, -1) - b**2, 0.0))
        disc = b**2 - (np.sum(oc * oc, -1) - self.radius**2)
        hit = disc > 0
        t = -b - np.sqrt(np.maximum(disc, 0.0))
        normal = (oc + t[:, None] * directions) / self.radius
        lambert = np.maximum(np.sum(normal * light, -1), 0.0)
        rgb = np.where(hit[:, None], np.asarray(self.albedo) * (self.ambient + lambert)[:, None], 0.0)
        zone = np.where(
            hit,
            ZONE_FOREGROUND,
            np.where(closest < self.radius * (1 + self.band), ZONE_BAND, ZONE_BACKGROUND),
        )
        return rgb.astype(np.float32), zone.astype(np.int64)

    def batch(self, step: int, rank: int = 0) -> dict[str, torch.Tensor]:
        """The batch for one (step, rank): deterministic, composed by zone like the shard loader."""
        rng = np.random.default_rng([self.seed, rank, step])
        n = 4 * self.batch_size
        c = np.asarray(self.centre)
        origins = c + self.camera_distance * _unit(rng.normal(size=(n, 3)))
        aim = c + rng.uniform(-1.0, 1.0, size=(n, 3)) * self.radius * 1.6
        directions = _unit(aim - origins)
        light = _unit(rng.normal(size=(n, 3)))
        rgb, zone = self.shade(origins, directions, light)
        counts = [int(round(f * self.batch_size)) for f in self.zone_fractions]
        counts[0] += self.batch_size - sum(counts)
        picks = []
        for z, count in zip((ZONE_FOREGROUND, ZONE_BAND, ZONE_BACKGROUND), counts, strict=True):
            idx = np.flatnonzero(zone == z)
            picks.append(idx[:count] if len(idx) >= count else rng.choice(idx, count))
        sel = rng.permutation(np.concatenate(picks))
        return {
            "origins": torch.from_numpy(origins[sel].astype(np.float32)),
            "directions": torch.from_numpy(directions[sel].astype(np.float32)),
            "light_positions": torch.from_numpy((c + 1.5 * light[sel]).astype(np.float32)),
            "light_directions": torch.from_numpy(light[sel].astype(np.float32)),
            "rgb": torch.from_numpy(rgb[sel]),
            "saturated": torch.zeros(len(sel), dtype=torch.bool),
            "zone": torch.from_numpy(zone[sel]),
        }

    def batches(
        self, start: int = 0, rank: int = 0, world_size: int = 1
    ) -> Iterator[dict[str, torch.Tensor]]:
        """Batches from position `start` on (BatchSource protocol)."""
        step = start
        while True:
            yield self.batch(step, rank)
            step += 1

    def camera(self, azimuth_deg: float, elevation_deg: float, size: int = 32) -> PinholeCamera:
        """A camera on the viewing sphere looking at the sphere centre."""
        az, el = np.deg2rad(azimuth_deg), np.deg2rad(elevation_deg)
        c = np.asarray(self.centre)
        pos = c + self.camera_distance * np.array(
            [np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)]
        )
        R, t = look_at(pos, c)
        f = 1.6 * size
        K = np.array([[f, 0.0, size / 2], [0.0, f, size / 2], [0.0, 0.0, 1.0]])
        return PinholeCamera(K, R, t, size, size)

    def test_images(self, count: int = 3, size: int = 32) -> list[TestImage]:
        """Held-out views and lights with analytic ground truth."""
        rng = np.random.default_rng([self.seed, 999])
        images = []
        for k in range(count):
            cam = self.camera(37.0 + 71.0 * k, 20.0 - 15.0 * k, size)
            light = _unit(rng.normal(size=3))
            o, d = pixel_rays(pixel_centers(size, size), cam.K, cam.R, cam.t)
            rgb, _ = self.shade(o.reshape(-1, 3), d.reshape(-1, 3), np.broadcast_to(light, (size * size, 3)))
            images.append(TestImage(f"sphere_{k:02d}", cam, light, rgb.reshape(size, size, 3)))
        return images


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)
