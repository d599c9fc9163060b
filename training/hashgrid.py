"""The `fast` field: a multiresolution hash encoding (Mueller et al. 2022) in pure PyTorch with small MLP heads.

Level l has resolution floor(base * b^l) with b chosen so the last level reaches `max_resolution`; coarse levels
whose (res+1)^3 vertices fit the table are indexed densely, finer ones through the spatial hash
(x*1 xor y*2654435761 xor z*805459861) mod T. Features are trilinearly interpolated from the 8 cell corners.
On CPU the lookup runs in the fused kernels of `hashgrid_cpu`; the PyTorch path below is CUDA's and the reference.
"""

from __future__ import annotations

import math
import os

import numpy as np
import torch
from torch import nn

from lightstage.training import fused_mlp, hashgrid_cpu
from lightstage.training.config import ModelConfig
from lightstage.training.encoding import encoded_dim, positional_encoding
from lightstage.training.heads import density_activation, exp_head

_FUSED_MLP = os.environ.get("LIGHTSTAGE_FUSED_MLP", "1") != "0"
PRIMES = (1, 2654435761, 805459861)
CORNERS = torch.tensor([[(c >> 0) & 1, (c >> 1) & 1, (c >> 2) & 1] for c in range(8)], dtype=torch.long)


class _WeightedLookup(torch.autograd.Function):
    """out[l, n] = sum_c w[c, l, n] * table[idx[c, l, n]] for a (rows, F) table, corners c first and samples
    last so every elementwise op runs over long contiguous rows. Forward: one gather, of the rows as single
    8-byte words when F * 4 == 8 (a 2-feature float32 row; ~10x faster than a 2-column index_select on CPU);
    backward: one weighted `bincount` per feature (~4x faster than `index_add_` or the scatter of
    `F.embedding`). No gradient flows to the weights: sample positions are not optimised."""

    @staticmethod
    def forward(ctx, table: torch.Tensor, idx: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
        flat = idx.reshape(-1)
        if table.dtype == torch.float32 and table.shape[1] == 2 and table.is_contiguous():
            feats = table.view(torch.int64).view(-1).index_select(0, flat).view(torch.float32)
        else:
            feats = table.index_select(0, flat)
        ctx.save_for_backward(idx, w)
        ctx.rows = table.shape[0]
        return (feats.view(*idx.shape, table.shape[1]) * w[..., None]).sum(0)  # (L, N, F)

    @staticmethod
    def backward(ctx, grad: torch.Tensor):
        idx, w = ctx.saved_tensors
        flat = idx.reshape(-1)
        g = torch.stack(
            [
                torch.bincount(flat, (w * grad[None, ..., f]).reshape(-1), ctx.rows).to(grad.dtype)
                for f in range(grad.shape[-1])
            ],
            dim=1,
        )
        return g, None, None


class HashGridEncoding(nn.Module):
    """(N, 3) points in [-1, 1]^3 -> (N, levels * features_per_level) interpolated hash-table features.

    All levels are looked up in one gather: the tables are one packed (sum of sizes, F) matrix, each level's
    indices offset by its first row (`_WeightedLookup`). Index and weight arithmetic runs on (levels, N)
    arrays, one per corner, with the hash in int32 (see `forward`)."""

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
        self.offsets = [sum(self.sizes[:level]) for level in range(levels + 1)]  # level l: rows [o_l, o_l+1)
        # One (sum of sizes, F) matrix, level after level: a dense level holds only its (res + 1)^3 rows, so
        # no padding rows are zeroed, optimised or saved (a third of `fast`'s 16 x 2^19 layout). Drawn as the
        # padded (L, T, F) table, then packed: the same initial values as that layout.
        padded = torch.empty(levels, self.table_size, features).uniform_(-1e-4, 1e-4)
        self.tables = nn.Parameter(self.packed(padded))
        self.register_buffer("row_offsets", torch.tensor(self.offsets[:-1]), persistent=False)
        self.output_dim = levels * features
        # the fused CPU kernels' per-level constants (hashgrid_cpu)
        self._kernel_args = (
            np.asarray(resolutions, dtype=np.float32),
            np.asarray(resolutions, dtype=np.int64),
            np.asarray(self.dense, dtype=np.bool_),
            np.asarray(self.offsets, dtype=np.int64),  # L + 1
            np.asarray([p & (self.table_size - 1) for p in PRIMES], dtype=np.int64),
        )
        if max(resolutions) + 1 >= 2**31 // self.table_size:
            raise ValueError("hash grid: max_resolution * table size must stay below 2^31")

    def packed(self, t: torch.Tensor) -> torch.Tensor:
        """The packed (sum of sizes, F) layout of a table in the padded (levels, T, F) layout of checkpoints
        written before the packing (each level's first `sizes[level]` rows); any other shape as it is."""
        if t.dim() == 3 and tuple(t.shape) == (self.levels, self.table_size, self.features):
            return torch.cat([t[level, :size] for level, size in enumerate(self.sizes)])
        return t

    def level_table(self, level: int) -> torch.Tensor:
        """Level `level`'s rows of the packed table, (sizes[level], F)."""
        return self.tables[self.offsets[level] : self.offsets[level + 1]]

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs):
        """Checkpoints with the padded (levels, T, F) table load into the packed one."""
        key = prefix + "tables"
        if key in state_dict:
            state_dict[key] = self.packed(state_dict[key])
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)

    def pack_optimizer_state(self, opt: torch.optim.Optimizer) -> None:
        """After loading an optimiser state written with the padded table: its per-parameter tensors (Adam's
        moments) packed like the table."""
        for key, value in opt.state.get(self.tables, {}).items():
            if torch.is_tensor(value):
                opt.state[self.tables][key] = self.packed(value)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        n = len(x)
        u = ((x.float() + 1.0) * 0.5).clamp(0.0, 1.0)
        if x.device.type == "cpu" and self.tables.dtype == torch.float32 and hashgrid_cpu.available():
            return hashgrid_cpu.FusedLookup.apply(self.tables, u, *self._kernel_args)  # (N, L * F)
        u = u.t()  # (3, N)
        res = self.resolutions
        pos = u[None] * res[:, None, None].float()  # (L, 3, N)
        cell = torch.minimum(pos.long(), (res - 1)[:, None, None])  # floor (pos >= 0)
        frac = pos - cell
        nd = sum(self.dense)
        idx = torch.empty(8, self.levels, n, dtype=torch.long, device=x.device)
        if nd:  # dense levels: idx = sum_a (cell_a + c_a) * stride^a = base + per-corner constant
            stride = (res[:nd] + 1)[:, None]
            c = cell[:nd]
            base = c[:, 0] + stride * (c[:, 1] + stride * c[:, 2])  # (nd, N)
            powers = torch.stack([torch.ones_like(stride), stride, stride * stride], 1)  # (nd, 3, 1)
            # an elementwise sum, not `@`: CUDA has no integer matmul ("baddbmm_cuda" not implemented for Long)
            steps = (CORNERS.to(x.device)[None, :, :, None] * powers[:, None]).sum(2)  # (nd, 8, 1)
            idx[:, :nd] = base[None] + steps.permute(1, 0, 2)  # (8, nd, N)
        if nd < self.levels:
            # Only the low log2(T) bits of the spatial hash are used, and (v * P) mod T = (v * (P mod T))
            # mod T, so the products stay inside int32: the same indices as the 64-bit hash.
            mask = self.table_size - 1
            c = cell[nd:].int()
            h = [[c[:, a] * (p & mask), (c[:, a] + 1) * (p & mask)] for a, p in enumerate(PRIMES)]
            for k in range(8):
                idx[k, nd:] = (h[0][k & 1] ^ h[1][(k >> 1) & 1] ^ h[2][(k >> 2) & 1]) & mask
        idx += self.row_offsets[None, :, None]
        wa = [(1.0 - frac[:, a], frac[:, a]) for a in range(3)]
        wxy = [wa[0][k & 1] * wa[1][k >> 1] for k in range(4)]
        w = torch.stack([wxy[k & 3] * wa[2][k >> 2] for k in range(8)])  # (8, L, N)
        out = _WeightedLookup.apply(self.tables, idx, w)  # (L, N, F)
        return out.permute(1, 0, 2).reshape(n, self.output_dim)


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
        head_in += encoded_dim(g.half_freqs) if g.half_freqs >= 0 else 0
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
        return self.geometry(x)[0]

    def geometry(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(sigma (N,), geometry features (N, geo_features)) at normalised positions (N, 3): the light- and
        view-independent stage."""
        geo = self.geo(self.encoding(x))
        return density_activation(geo[..., 0], self.cfg.density_activation, self.cfg.density_bias), geo[
            ..., 1:
        ]

    def transfer(
        self,
        features: torch.Tensor,
        view: torch.Tensor,
        light: torch.Tensor,
        rows: torch.Tensor | None = None,
        per_ray_light: bool = False,
    ) -> torch.Tensor:
        """(N, 3) transfer gradient h from geometry features (N, F) and unit view / light directions (N, 3),
        or, given `rows` (N,) (each sample's ray), the view per ray (R, 3), and the light too when
        `per_ray_light`. The head's first layer is linear in [features, PE(view), PE(light), PE(half)], so
        per-ray inputs are encoded and multiplied once per ray and gathered, not once per sample."""
        g = self.cfg.hashgrid
        first = self.head[0]
        nf, w = features.shape[1], first.weight
        by_ray = rows is not None and per_ray_light  # light (and half vector) per ray too
        per_ray = [positional_encoding(view, g.dir_freqs)]
        per_sample: list[torch.Tensor] = []
        (per_ray if by_ray else per_sample).append(positional_encoding(light, g.light_freqs))
        if g.half_freqs >= 0:  # view: the ray direction, into the scene
            v = view[rows] if rows is not None and not by_ray else view
            half = positional_encoding(torch.nn.functional.normalize(light - v, dim=-1), g.half_freqs)
            (per_ray if by_ray else per_sample).append(half)
        nr = sum(t.shape[1] for t in per_ray)
        ray_term = torch.cat(per_ray, -1) @ w[:, nf : nf + nr].t()
        pre = torch.nn.functional.linear(features, w[:, :nf], first.bias)
        pre = pre + (ray_term if rows is None else ray_term[rows])
        if per_sample:
            pre = pre + torch.cat(per_sample, -1) @ w[:, nf + nr :].t()
        for module in self.head[1:]:
            pre = module(pre)
        return exp_head(pre, self.cfg.h_max_exponent)

    def fused_available(self, x: torch.Tensor) -> bool:
        """Whether `geometry_and_transfer` runs the chunked MLPs (`fused_mlp`): on CPU, float32, outside autocast."""
        return x.device.type == "cpu" and not torch.is_autocast_enabled("cpu") and _FUSED_MLP

    def geometry_and_transfer(
        self, x: torch.Tensor, view: torch.Tensor, light: torch.Tensor, rows: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """(sigma (N,), h (N, 3)) at normalised positions x (N, 3) of rays `rows` (N,) with the view and light
        per ray (R, 3): `geometry` then `transfer(..., per_ray_light=True)` through `fused_mlp.field_mlp`."""
        g = self.cfg.hashgrid
        first = self.head[0]
        nf = g.geo_features
        per_ray = [positional_encoding(view, g.dir_freqs), positional_encoding(light, g.light_freqs)]
        if g.half_freqs >= 0:
            per_ray.append(
                positional_encoding(torch.nn.functional.normalize(light - view, dim=-1), g.half_freqs)
            )
        ray_term = torch.cat(per_ray, -1) @ first.weight[:, nf:].t()
        geo_out, raw = fused_mlp.field_mlp(
            self.encoding(x),
            ray_term,
            rows,
            [(m.weight, m.bias) for m in self.geo[::2]],
            [(first.weight[:, :nf], first.bias)] + [(m.weight, m.bias) for m in self.head[2::2]],
        )
        sigma = density_activation(geo_out[:, 0], self.cfg.density_activation, self.cfg.density_bias)
        return sigma, exp_head(raw, self.cfg.h_max_exponent)

    def forward(
        self, x: torch.Tensor, view: torch.Tensor, light: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """(sigma (N,), h (N, 3)) at normalised positions x with unit view and light directions (N, 3)."""
        sigma, features = self.geometry(x)
        return sigma, self.transfer(features, view, light)
