"""Where samples go along each ray: ray-box intersection with the unit cube, stratified intervals, and
hierarchical resampling of a piecewise-constant pdf (intervals as edges, samples at midpoints, as in multinerf)."""

from __future__ import annotations

import torch


def ray_box(
    origins: torch.Tensor,
    directions: torch.Tensor,
    lo: torch.Tensor | float = -1.0,
    hi: torch.Tensor | float = 1.0,
) -> tuple[torch.Tensor, torch.Tensor]:
    """(near, far) of rays (normalised coordinates) inside the box [lo, hi] (scalars or (3,) corners; default
    the unit cube [-1, 1]^3); rays that miss get far = near."""
    safe = torch.where(directions.abs() < 1e-12, torch.full_like(directions, 1e-12), directions)
    inv = 1.0 / safe
    t0 = (lo - origins) * inv
    t1 = (hi - origins) * inv
    near = torch.minimum(t0, t1).amax(-1).clamp(min=0.0)
    far = torch.maximum(t0, t1).amin(-1)
    return near, torch.maximum(far, near)


def stratified_edges(near: torch.Tensor, far: torch.Tensor, n: int, randomized: bool) -> torch.Tensor:
    """(R, n+1) interval edges spanning [near, far]; interior edges jittered within their bins when randomized."""
    s = torch.linspace(0.0, 1.0, n + 1, device=near.device).expand(near.shape[0], n + 1)
    if randomized and n > 1:
        jitter = (torch.rand(near.shape[0], n - 1, device=near.device) - 0.5) / n
        s = torch.cat([s[:, :1], s[:, 1:-1] + jitter, s[:, -1:]], dim=-1)
    return near[:, None] + (far - near)[:, None] * s


def resample_edges(
    edges: torch.Tensor, weights: torch.Tensor, n: int, randomized: bool, padding: float
) -> torch.Tensor:
    """(R, n+1) new edges drawn from the piecewise-constant pdf `weights` on `edges` (inverse CDF)."""
    w = (
        weights.detach()
        + padding * weights.detach().sum(-1, keepdim=True).clamp(min=1e-5) / weights.shape[-1]
    )
    w = w + 1e-8
    cdf = torch.cumsum(w, dim=-1)
    cdf = torch.cat([torch.zeros_like(cdf[:, :1]), cdf / cdf[:, -1:]], dim=-1)  # (R, S+1)
    u = torch.linspace(0.0, 1.0, n + 1, device=edges.device).expand(edges.shape[0], n + 1).contiguous()
    if randomized and n > 1:
        jitter = (torch.rand(edges.shape[0], n - 1, device=edges.device) - 0.5) / n
        u = torch.cat([u[:, :1], u[:, 1:-1] + jitter, u[:, -1:]], dim=-1)
    idx = torch.searchsorted(cdf, u, right=True).clamp(1, cdf.shape[-1] - 1)
    c0, c1 = cdf.gather(-1, idx - 1), cdf.gather(-1, idx)
    e0, e1 = edges.gather(-1, idx - 1), edges.gather(-1, idx)
    frac = ((u - c0) / (c1 - c0).clamp(min=1e-12)).clamp(0.0, 1.0)
    return e0 + frac * (e1 - e0)


def merge_edges(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Sorted union of two edge sets per ray (the fine pass sees the coarse and the resampled edges, like NeRF)."""
    return torch.sort(torch.cat([a, b], dim=-1), dim=-1).values


def midpoints(edges: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(t, delta): interval midpoints and lengths of (R, S+1) edges."""
    return 0.5 * (edges[:, 1:] + edges[:, :-1]), edges[:, 1:] - edges[:, :-1]
