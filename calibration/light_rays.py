"""Rig-frame light positions from rays that point at the lights, whatever observed them.

A bulb seen directly gives a ray from the camera centre through the disc (`bulbs.py`); a highlight on a
mirror ball gives the ball's reflection of the camera ray (`probe.py`). Both end up as a `LightRay`: a point,
a unit direction and an angular uncertainty across the direction. This module turns rays into

- `locate_lights`: the final rig-frame positions, the least-squares point of each light's rays with its
  nominal position as a prior (per-axis `prior_sigma_m`), after dropping rays that miss that point by more
  than `max_ray_sigma` of their own uncertainty (a wrong blob);
- `gauge_points`: observed lights as extra nominal points for the world-frame gauge (`register.fit_gauge`),
  weighted by how well the rays fix them combined with the lights' mounting tolerance.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True)
class LightRay:
    """A ray towards light `light` in the rig frame (metres): origin, unit direction, angular std (radians)."""

    light: int
    origin: np.ndarray
    direction: np.ndarray
    sigma_rad: float
    source: str  # what observed it, e.g. "bulb cam03" or "probe 120/cam03"


@dataclass
class LightEstimate:
    """Rig-frame light positions (metres) and how each was obtained."""

    positions: np.ndarray  # (L, 3) stage rig frame
    sources: dict[int, list[str]] = field(default_factory=dict)  # light -> what observed it (rays kept)
    shift_mm: dict[int, float] = field(default_factory=dict)  # light -> distance from nominal
    sigma_mm: dict[int, float] = field(default_factory=dict)  # light -> largest posterior std (mm)
    rejected_rays: dict[int, int] = field(default_factory=dict)  # light -> rays dropped as outliers


def _ray_sigma_m(ray: LightRay, target: np.ndarray) -> float:
    """The ray's std across its direction (metres) at the distance of `target`."""
    return max(float(np.linalg.norm(target - ray.origin)), 1e-6) * ray.sigma_rad


def _normal_equations(rays: list[LightRay], target: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A = sum P_i / s_i^2, b = sum P_i o_i / s_i^2 (P_i projects across ray i, s_i its std near `target`)."""
    A, b = np.zeros((3, 3)), np.zeros(3)
    for r in rays:
        d = np.asarray(r.direction, np.float64)
        P = (np.eye(3) - np.outer(d, d)) / _ray_sigma_m(r, target) ** 2
        A += P
        b += P @ np.asarray(r.origin, np.float64)
    return A, b


def ray_misfit(ray: LightRay, point: np.ndarray) -> float:
    """How far `point` lies from the ray, in units of the ray's own std there."""
    v = np.asarray(point, np.float64) - ray.origin
    off = v - (v @ ray.direction) * ray.direction
    return float(np.linalg.norm(off) / _ray_sigma_m(ray, point))


def _by_light(rays: list[LightRay]) -> dict[int, list[LightRay]]:
    out: dict[int, list[LightRay]] = {}
    for r in rays:
        out.setdefault(r.light, []).append(r)
    return dict(sorted(out.items()))


def _solve(A: np.ndarray, b: np.ndarray, prior: np.ndarray, w: float) -> np.ndarray:
    return np.linalg.solve(A + w * np.eye(3), b + w * prior)


def _drop_outliers(
    rays: list[LightRay], solve: Callable[[list[LightRay]], np.ndarray], max_ray_sigma: float
) -> tuple[list[LightRay], np.ndarray | None]:
    """Solve, then drop the ray that misses the point worst while it misses by more than `max_ray_sigma` of its
    std (one at a time: a wrong ray pulls the first point off every ray). Returns (rays kept, point)."""
    keep = list(rays)
    while keep:
        p = solve(keep)
        misfit = [ray_misfit(r, p) for r in keep]
        worst = int(np.argmax(misfit))
        if misfit[worst] <= max_ray_sigma or len(keep) == 1:
            return keep, p
        keep.pop(worst)
    return keep, None


def locate_lights(
    rays: list[LightRay],
    nominal_rig: np.ndarray,
    prior_sigma_m: float = 0.003,
    max_ray_sigma: float = 5.0,
) -> LightEstimate:
    """Each observed light at the least-squares point of its rays with the nominal position as prior, after
    dropping rays that miss it by more than `max_ray_sigma` of their std; lights without rays keep their
    nominal positions."""
    nominal_rig = np.asarray(nominal_rig, np.float64)
    est = LightEstimate(nominal_rig.copy())
    w = 1.0 / prior_sigma_m**2
    for li, mine in _by_light(rays).items():
        prior = nominal_rig[li]
        keep, p = _drop_outliers(
            mine, lambda rs, prior=prior: _solve(*_normal_equations(rs, prior), prior, w), max_ray_sigma
        )
        if len(keep) < len(mine):
            est.rejected_rays[li] = len(mine) - len(keep)
        A, _ = _normal_equations(keep, p)
        est.positions[li] = p
        est.sources[li] = [r.source for r in keep]
        est.shift_mm[li] = float(1000.0 * np.linalg.norm(p - prior))
        cov = np.linalg.inv(A + w * np.eye(3))
        est.sigma_mm[li] = float(1000.0 * np.sqrt(np.linalg.eigvalsh(cov)[-1]))
    return est


def gauge_points(
    rays: list[LightRay],
    nominal_rig: np.ndarray,
    mount_sigma_m: float = 0.003,
    max_ray_sigma: float = 5.0,
) -> tuple[list[int], np.ndarray, np.ndarray, np.ndarray]:
    """Observed lights as extra points of the gauge fit: (lights, points in the frame of the rays, their nominal
    positions, (N, 3, 3) square-root information matrices in metres^-1).

    A light's point is the least-squares point of its rays (for a single ray: the ray's point closest to the
    nominal position). The nominal position misses the true one by the mounting tolerance `mount_sigma_m` per
    axis, and the rays fix the true one with information A, so the residual point - nominal has information
    A (I + sigma^2 A)^-1: isotropic for a triangulated light, zero along the ray of a light seen once.
    """
    nominal_rig = np.asarray(nominal_rig, np.float64)
    lights, pts, nom, sqrt_info = [], [], [], []
    for li, mine in _by_light(rays).items():
        prior = nominal_rig[li]

        def solve(rs: list[LightRay], prior: np.ndarray = prior) -> np.ndarray:
            A, b = _normal_equations(rs, prior)
            return _solve(A, b, prior, 1e-6 * np.trace(A))  # a single ray: its point closest to the nominal

        keep, p = _drop_outliers(mine, solve, max_ray_sigma)
        A, _ = _normal_equations(keep, prior)
        pts.append(p)
        info = A @ np.linalg.inv(np.eye(3) + mount_sigma_m**2 * A)
        vals, vecs = np.linalg.eigh(0.5 * (info + info.T))
        sqrt_info.append(vecs @ np.diag(np.sqrt(np.clip(vals, 0.0, None))) @ vecs.T)
        nom.append(prior)
        lights.append(li)
    if not lights:
        return [], np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 3, 3))
    return lights, np.stack(pts), np.stack(nom), np.stack(sqrt_info)
