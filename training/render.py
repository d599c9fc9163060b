"""Volume rendering of the transfer gradient (paper Eq. 1): pixel = sum_i w_i h_i, w_i = T_i (1 - exp(-sigma_i delta_i))."""

from __future__ import annotations

import torch


def volume_weights(sigma: torch.Tensor, delta: torch.Tensor) -> torch.Tensor:
    """(R, S) NeRF weights from densities and interval lengths; T_i = exp(-sum_{j<i} sigma_j delta_j)."""
    sd = sigma * delta
    alpha = 1.0 - torch.exp(-sd)
    trans = torch.exp(-torch.cat([torch.zeros_like(sd[:, :1]), torch.cumsum(sd[:, :-1], dim=-1)], dim=-1))
    return alpha * trans


def composite(weights: torch.Tensor, values: torch.Tensor) -> torch.Tensor:
    """(R, C) weighted sum over samples of (R, S, C) values."""
    return (weights[..., None] * values).sum(dim=-2)


def composite_rows(
    weights: torch.Tensor, values: torch.Tensor, rows: torch.Tensor, n_rays: int
) -> torch.Tensor:
    """(R, C) weighted sum of the kept samples' values (N, C) with weights (N,) into their rays `rows` (N,):
    `composite` over only the samples that exist, without scattering them into an (R, S, C) array first."""
    return values.new_zeros(n_rays, values.shape[1]).index_add_(0, rows, weights[:, None] * values)
