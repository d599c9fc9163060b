"""The `fast` field: a multiresolution hash encoding (Mueller et al. 2022) in pure PyTorch with small MLP heads.

Level l has resolution floor(base * b^l) with b chosen so the last level reaches `max_resolution`; coarse levels
whose (res+1)^3 vertices fit the table are indexed densely, finer ones through the spatial hash
(x*1 xor y*2654435761 xor z*805459861) mod T. Features are trilinearly interpolated from the 8 cell corners.
"""

from __future__ import annotations

import math

import torch
from torch import nn

from lightstage.training.config import ModelConfig
from lightstage.training.encoding import encoded_dim, positional_encoding
from lightstage.training.heads import density_activation, exp_head

PRIMES = (1, 2654435761, 805459861)
CORNERS = torch.tensor([[(c >> 0) & 1, (c >> 1) & 1, (c >> 2) & 1] for c in range(8)], dtype=torch.long)


class HashGridEncoding(nn.Module):
    """(N, 3) points in [-1, 1]^3 -> (N, levels * features_per_level) interpolated hash-table features."""

    def __init__(
        self, levels: int, features: int, log2_table_size: int, base_resolution: int, max_resolution: int
    ):
        super().__init__()
        self.table_size = 2**log2_table_size
        growth = math.exp((math.log(max_resolution) - math.log(base_resolution)) / max(levels - 1, 1))
        resolutions = [int(math.floor(base_resolution * growth**level)) for level in range(levels)]
        self.register_buffer("resolutions", torch.tensor(resolutions, dtype=torch.long), persistent=False)
        self.dense = [(r + 1) ** 3 <= self.table_size for r in resolutions]
        self.sizes = [min((r + 1) ** 3, self.table_size) for r in resolutions]
        self.tables = nn.Parameter(torch.empty(levels, self.table_size, features).uniform_(-1e-4, 1e-4))
        self.output_dim = levels * features

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        u = ((x.float() + 1.0) * 0.5).clamp(0.0, 1.0)
        corners = CORNERS.to(x.device)
        out = []
        for level, res in enumerate(self.resolutions.tolist()):
            pos = u * res
            cell = torch.floor(pos).long().clamp(max=res - 1)
            frac = pos - cell  # (N, 3)
            vertex = cell[:, None, :] + corners  # (N, 8, 3)
            if self.dense[level]:
                idx = vertex[..., 0] + (res + 1) * (vertex[..., 1] + (res + 1) * vertex[..., 2])
            else:
                idx = (
                    (vertex[..., 0] * PRIMES[0]) ^ (vertex[..., 1] * PRIMES[1]) ^ (vertex[..., 2] * PRIMES[2])
                )
                idx = idx % self.table_size
            w = torch.where(corners.bool(), frac[:, None, :], 1.0 - frac[:, None, :]).prod(-1)  # (N, 8)
            out.append((self.tables[level][idx] * w[..., None]).sum(1))
        return torch.cat(out, dim=-1)


class HashGridField(nn.Module):
    """Hash encoding -> density MLP (sigma + geometry features) -> head on [features, view, light] -> exp(h)."""

    def __init__(self, cfg: ModelConfig):
        super().__init__()
        g = cfg.hashgrid
        self.cfg = cfg
        self.encoding = HashGridEncoding(
            g.levels, g.features_per_level, g.log2_table_size, g.base_resolution, g.max_resolution
        )
        self.geo = nn.Sequential(
            nn.Linear(self.encoding.output_dim, g.hidden), nn.ReLU(), nn.Linear(g.hidden, 1 + g.geo_features)
        )
        head_in = g.geo_features + encoded_dim(g.dir_freqs) + encoded_dim(g.light_freqs)
        self.head = nn.Sequential(
            nn.Linear(head_in, g.hidden),
            nn.ReLU(),
            nn.Linear(g.hidden, g.hidden),
            nn.ReLU(),
            nn.Linear(g.hidden, 3),
        )
        nn.init.constant_(self.head[-1].bias, cfg.h_bias_init)

    def density(self, x: torch.Tensor) -> torch.Tensor:
        """(N,) density at normalised positions (N, 3)."""
        raw = self.geo(self.encoding(x))[..., 0]
        return density_activation(raw, self.cfg.density_activation, self.cfg.density_bias)

    def forward(
        self, x: torch.Tensor, view: torch.Tensor, light: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """(sigma (N,), h (N, 3)) at normalised positions x with unit view and light directions (N, 3)."""
        g = self.cfg.hashgrid
        geo = self.geo(self.encoding(x))
        sigma = density_activation(geo[..., 0], self.cfg.density_activation, self.cfg.density_bias)
        head_in = torch.cat(
            [geo[..., 1:], positional_encoding(view, g.dir_freqs), positional_encoding(light, g.light_freqs)],
            -1,
        )
        return sigma, exp_head(self.head(head_in), self.cfg.h_max_exponent)
