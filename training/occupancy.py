"""Occupancy grid over the normalised unit cube (instant-ngp style) to skip evaluating empty space.

Each cell keeps a decaying maximum of the density seen at random points inside it; samples that fall in cells
whose density would give alpha < min_alpha at the nominal step size are not evaluated (sigma = 0, h = 0).
Updates draw their points from a generator seeded by (seed, step), so DDP ranks and resumed runs agree.
Only cells of the grid's *region* are updated (the visual-hull prior, else the cells overlapping the scene box):
samples never leave the box, and outside the hull the masks say there is nothing; on the demo capture that is
~1/8 of the cells for the box and fewer for the hull, so an update costs that much less, and cells outside the hull
cannot fill with the untrained field's density (they did: 80 % of the cube read as occupied after training).
"""

from __future__ import annotations

import math
from collections.abc import Callable

import torch
from torch import nn

PRIOR_FACTOR = 2.0  # prior cells stay occupied for log(2) / -log(decay) updates without density support


class OccupancyGrid(nn.Module):
    """A res^3 density grid over [-1, 1]^3; everything counts as occupied until the first update."""

    def __init__(
        self, resolution: int, decay: float, density_threshold: float, region: torch.Tensor | None = None
    ):
        super().__init__()
        self.resolution = resolution
        self.decay = decay
        self.density_threshold = density_threshold
        self.register_buffer("grid", torch.zeros(resolution, resolution, resolution))
        self.register_buffer("ready", torch.zeros((), dtype=torch.bool))
        # cells that updates evaluate (bool res^3; not saved: rebuilt from the box / hull with the model)
        full = torch.ones((resolution,) * 3, dtype=torch.bool)
        self.register_buffer("region", full if region is None else region.bool().clone(), persistent=False)

    def cell_index(self, x: torch.Tensor) -> torch.Tensor:
        """Integer (..., 3) cell indices of normalised points (clamped into the grid)."""
        return ((x + 1.0) * 0.5 * self.resolution).long().clamp(0, self.resolution - 1)

    def occupied(self, x: torch.Tensor) -> torch.Tensor:
        """Boolean (...) mask: does the cell containing each normalised point (..., 3) hold matter?"""
        if not bool(self.ready):
            return torch.ones(x.shape[:-1], dtype=torch.bool, device=x.device)
        i = self.cell_index(x)
        return self.grid[i[..., 0], i[..., 1], i[..., 2]] > self.density_threshold

    @torch.no_grad()
    def update(
        self, density_fn: Callable[[torch.Tensor], torch.Tensor], seed: int, chunk: int = 65536
    ) -> None:
        """grid <- max(decay * grid, density at one random point per cell of the region; 0 elsewhere)."""
        r = self.resolution
        device = self.grid.device
        gen = torch.Generator(device="cpu").manual_seed(int(seed))
        cells = self.region.reshape(-1).nonzero(as_tuple=True)[0].cpu()  # random points for these cells only
        ijk = torch.stack([cells // (r * r), cells // r % r, cells % r], -1)
        pts = ((ijk + torch.rand(ijk.shape, generator=gen)) / r * 2.0 - 1.0).to(device)
        dens = torch.zeros(r**3, device=device)
        if len(cells):
            dens[cells.to(device)] = torch.cat(
                [density_fn(pts[i : i + chunk]).float() for i in range(0, len(pts), chunk)]
            )
        self.grid.copy_(torch.maximum(self.grid * self.decay, dens.reshape(r, r, r)))
        self.ready.fill_(True)

    @torch.no_grad()
    def set_prior(self, prior: torch.Tensor) -> None:
        """Start from a known superset of the matter (e.g. the visual hull): cells outside it are empty from
        step 0 (no all-occupied warm-up), cells inside it start `PRIOR_FACTOR` x the threshold and fade with
        the decay once density updates begin; updates evaluate only the prior's cells from then on."""
        self.grid.copy_(prior.to(self.grid).float() * PRIOR_FACTOR * self.density_threshold)
        self.region.copy_(prior.to(self.region.device).bool())
        self.ready.fill_(True)

    def occupied_fraction(self) -> float:
        return float((self.grid > self.density_threshold).float().mean()) if bool(self.ready) else 1.0


def density_threshold(min_alpha: float, n_samples: int) -> float:
    """Density whose alpha over the nominal step (cube diagonal / n_samples) equals min_alpha."""
    step = 2.0 * math.sqrt(3.0) / n_samples
    return -math.log(1.0 - min_alpha) / step


def box_cells(box_min: torch.Tensor, box_max: torch.Tensor, resolution: int) -> torch.Tensor:
    """(res, res, res) bool: occupancy cells over [-1, 1]^3 that overlap the normalised box [box_min, box_max]."""
    edges = torch.linspace(-1.0, 1.0, resolution + 1)
    axes = [(edges[1:] >= box_min[a]) & (edges[:-1] <= box_max[a]) for a in range(3)]
    return axes[0][:, None, None] & axes[1][None, :, None] & axes[2][None, None, :]


def hull_prior(
    hull: torch.Tensor, box_min: torch.Tensor, box_max: torch.Tensor, resolution: int, samples: int = 3
) -> torch.Tensor:
    """(res, res, res) bool: occupancy cells over [-1, 1]^3 that overlap the voxel hull (n0, n1, n2) tiling the
    normalised box [box_min, box_max], dilated by one hull voxel; each cell is probed at samples^3 points."""
    hull = hull.float()[None, None]
    hull = torch.nn.functional.max_pool3d(hull, 3, stride=1, padding=1)[0, 0] > 0
    n = torch.tensor(hull.shape, dtype=torch.float32)
    sub = (torch.arange(samples, dtype=torch.float32) + 0.5) / samples
    axis = (torch.arange(resolution, dtype=torch.float32)[:, None] + sub[None]).reshape(
        -1
    ) / resolution * 2 - 1
    # The probe points are a tensor product of per-axis coordinates, so each axis is mapped to hull voxel indices
    # on its own and the hull is gathered once over their outer product (56 MB of bools at 128^3 x 3^3; the
    # (N, 3) point list it replaces took GBs).
    idx, ok = [], []
    for a in range(3):
        rel = (axis - box_min[a]) / (box_max[a] - box_min[a]) * n[a]
        ok.append((rel >= 0) & (rel < n[a]))
        idx.append(rel.clamp(min=0).long().clamp(max=int(n[a]) - 1))
    hit = hull[idx[0][:, None, None], idx[1][None, :, None], idx[2][None, None, :]]
    hit &= ok[0][:, None, None] & ok[1][None, :, None] & ok[2][None, None, :]
    hit = hit.reshape(resolution, samples, resolution, samples, resolution, samples)
    return hit.any(5).any(3).any(1)
