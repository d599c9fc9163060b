"""Point lights at a finite distance (`model.light: point`): the capture's lights are ~1.5 m from a ~0.1 m object,
so the direction to the light and its inverse-square falloff vary across the object by several percent. The
model's interface keeps the paper's ω = normalize(p_light − c) from the light centre c; the model stores c and the
light distance R (measured from the training lights' positions) and rebuilds p_light = c + R ω per ray."""

from __future__ import annotations

import numpy as np
import torch


def light_frame(positions: np.ndarray, directions: np.ndarray) -> tuple[np.ndarray, float]:
    """(centre c, radius R) with positions ≈ c + R * directions: c is the least-squares meeting point of the
    lines p_i − t ω_i, R the median of ω_i · (p_i − c). Raises ValueError when the directions do not span
    two independent axes (c undetermined) or a light lies behind c."""
    p = np.asarray(positions, np.float64).reshape(-1, 3)
    w = np.asarray(directions, np.float64).reshape(-1, 3)
    w = w / np.linalg.norm(w, axis=1, keepdims=True)
    proj = np.eye(3)[None] - w[:, :, None] * w[:, None, :]  # (N, 3, 3) projections orthogonal to ω_i
    a, b = proj.sum(0), np.einsum("nij,nj->i", proj, p)
    if np.linalg.svd(a, compute_uv=False)[-1] < 1e-6 * len(p):
        raise ValueError("light directions do not determine a centre (all lights along one axis)")
    centre = np.linalg.solve(a, b)
    along = np.einsum("ni,ni->n", w, p - centre)
    if along.min() <= 0:
        raise ValueError("a light lies behind the centre its direction is measured from")
    return centre, float(np.median(along))


def point_light(x: torch.Tensor, light_pos: torch.Tensor, radius: float) -> tuple[torch.Tensor, torch.Tensor]:
    """(unit directions (..., 3) from points x towards the light, falloff (...,) = radius² / |p − x|²): the
    inverse-square irradiance relative to the light centre's, 1 at distance `radius` (all in one unit)."""
    v = light_pos - x
    d2 = (v * v).sum(-1).clamp(min=1e-12)
    return v * torch.rsqrt(d2)[..., None], radius * radius / d2
