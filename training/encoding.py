"""Positional (Fourier) encoding of positions and directions, as in NeRF."""

from __future__ import annotations

import math

import torch


def encoded_dim(n_freqs: int, dim: int = 3) -> int:
    """Width of `positional_encoding` output for `dim` inputs: the input plus sin and cos per frequency."""
    return dim * (1 + 2 * n_freqs)


def positional_encoding(x: torch.Tensor, n_freqs: int) -> torch.Tensor:
    """[x, sin(2^k x), cos(2^k x)] for k < n_freqs (cos as a phase-shifted sin, one sin call)."""
    if n_freqs == 0:
        return x
    scales = 2.0 ** torch.arange(n_freqs, device=x.device, dtype=x.dtype)
    xb = (x[..., None, :] * scales[:, None]).flatten(-2)  # (..., F*dim)
    return torch.cat([x, torch.sin(torch.cat([xb, xb + 0.5 * math.pi], dim=-1))], dim=-1)
