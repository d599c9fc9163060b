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


class _WeightedLookup(torch.autograd.Function):
    """out[n, l] = sum_c w[n, l, c] * table[idx[n, l, c]]: a gather forward and one `index_add_` backward (on
    CPU several times faster than the scatter of `F.embedding` or advanced indexing). No gradient flows to
    the weights: sample positions are not optimised."""

    @staticmethod
    def forward(ctx, table: torch.Tensor, idx: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
        n, levels, corners = idx.shape
        feats = table.index_select(0, idx.reshape(-1)).view(n, levels, corners, table.shape[1])
        ctx.save_for_backward(idx, w)
        ctx.rows = table.shape[0]
        return torch.einsum("nlcf,nlc->nlf", feats, w)

    @staticmethod
    def backward(ctx, grad: torch.Tensor):
        idx, w = ctx.saved_tensors
        per_corner = (grad[:, :, None, :] * w[..., None]).reshape(-1, grad.shape[-1])
        g = torch.zeros(ctx.rows, grad.shape[-1], dtype=grad.dtype, device=grad.device)
        g.index_add_(0, idx.reshape(-1), per_corner)
        return g, None, None


class HashGridEncoding(nn.Module):
    """(N, 3) points in [-1, 1]^3 -> (N, levels * features_per_level) interpolated hash-table features.

    All levels are looked up in one gather: the tables are one (levels * T, F) matrix, each level's indices
    offset by level * T (`_WeightedLookup`)."""

    def __init__(
        self, levels: int, features: int, log2_table_size: int, base_resolution: int, max_resolution: int
    ):
        super().__init__()
        self.table_size = 2**log2_table_size
        self.levels, self.features = levels, features
        growth = math.exp((math.log(max_resolution) - math.log(base_resolution)) / max(levels - 1, 1))
        resolutions = [int(math.floor(base_resolution * growth**level)) for level in range(levels)]
        self.register_buffer("resolutions", torch.tensor(resolutions, dtype=torch.long), persistent=False)
        self.dense = [(r + 1) ** 3 <= self.table_size for r in resolutions]
        self.sizes = [min((r + 1) ** 3, self.table_size) for r in resolutions]
        self.register_buffer("_dense", torch.tensor(self.dense), persistent=False)
        self.register_buffer(
            "_offsets", torch.arange(levels, dtype=torch.long) * self.table_size, persistent=False
        )
        self.tables = nn.Parameter(torch.empty(levels, self.table_size, features).uniform_(-1e-4, 1e-4))
        self.output_dim = levels * features

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        u = ((x.float() + 1.0) * 0.5).clamp(0.0, 1.0)
        res = self.resolutions  # (L,)
        pos = u[:, None, :] * res[None, :, None].float()  # (N, L, 3)
        cell = torch.minimum(pos.long(), (res - 1)[None, :, None])  # floor (pos >= 0)
        frac = pos - cell
        # Per axis, the two vertex coordinates of the cell: (N, L, 3, 2). Corner c = c0 + 2 c1 + 4 c2 combines
        # them by broadcasting (z, y, x) -> (..., 2, 2, 2) -> 8, so no (N, L, 8, 3) tensor is formed.
        vert = cell[..., None] + torch.arange(2, device=x.device)
        n_dense = sum(self.dense)
        parts = []
        if n_dense:
            stride = (res[:n_dense] + 1)[None, :, None]
            v = vert[:, :n_dense]
            parts.append(_corners(v[:, :, 0], v[:, :, 1] * stride, v[:, :, 2] * stride * stride, torch.add))
        if n_dense < self.levels:
            v = vert[:, n_dense:]
            h = _corners(
                v[:, :, 0] * PRIMES[0], v[:, :, 1] * PRIMES[1], v[:, :, 2] * PRIMES[2], torch.bitwise_xor
            )
            parts.append(h & (self.table_size - 1))  # == mod T (T is a power of two, the xor is >= 0)
        idx = (torch.cat(parts, 1) if len(parts) > 1 else parts[0]) + self._offsets[
            None, :, None
        ]  # (N, L, 8)
        wf = torch.stack([1.0 - frac, frac], -1)  # (N, L, 3, 2)
        w = _corners(wf[:, :, 0], wf[:, :, 1], wf[:, :, 2], torch.mul)  # (N, L, 8)
        out = _WeightedLookup.apply(self.tables.view(-1, self.features), idx, w)
        return out.reshape(len(x), self.output_dim)


def _corners(x: torch.Tensor, y: torch.Tensor, z: torch.Tensor, op) -> torch.Tensor:
    """(N, L, 8) op-combination of per-axis (N, L, 2) terms for the 8 cell corners in CORNERS order."""
    xy = op(y[..., :, None], x[..., None, :])  # (N, L, 2[c1], 2[c0])
    return op(z[..., :, None, None], xy[..., None, :, :]).flatten(-3)


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
