"""Image-based relighting from a basis of OLAT images (Debevec et al. 2000): light transport is linear, so the
image under any light is a weighted sum of the basis images taken under known light directions. This module is
the ONE definition of the weights, used by the viewer (`lightstage view`) and `lightstage relight --lights stage`:

* a point light (a direction on the stage sphere) gets barycentric weights on the spherical triangulation of
  the basis directions (the facets of their convex hull, seen from the centre): a light exactly at a basis
  light reproduces that basis image, and the weights vary continuously between lights. Directions outside the
  triangulated cap (below the lowest stage lights, say) take the weights of the nearest point of its rim.
* an environment map: every pixel is a light at its centre direction (rotation applied) carrying its RGB
  energy radiance x solid angle, distributed over the basis lights by the point-light weights and scaled by the
  irradiance-to-OLAT factor d^2 / I (docs/relighting.md).

Weights are (L, 3): one RGB factor per basis light, so relit = sum_l weights[l] * basis[l] per channel.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lightstage.errors import LightstageError
from lightstage.training.envmap import EnvMap, Lights, all_pixel_lights

COVER_EPS = 1e-9  # barycentric coordinates this far below 0 still count as inside a facet


@dataclass(frozen=True)
class LightBasis:
    """Unit basis light directions (L, 3), world frame, and the triangles (T, 3) of their spherical
    triangulation (indices into `directions`); `rim` (E, 2) are the edges of the triangulated region's border
    (empty when the triangles cover the whole sphere)."""

    directions: np.ndarray
    triangles: np.ndarray
    rim: np.ndarray

    def __len__(self) -> int:
        return int(self.directions.shape[0])

    @classmethod
    def of(cls, directions: np.ndarray) -> LightBasis:
        """Triangulate unit directions (normalised here; repeated directions are an error)."""
        d = np.asarray(directions, np.float64).reshape(-1, 3)
        norms = np.linalg.norm(d, axis=1)
        if len(d) == 0 or not np.all(norms > 0) or not np.all(np.isfinite(d)):
            raise LightstageError("light basis: need at least one finite, non-zero light direction")
        d = d / norms[:, None]
        gap = _min_angle(d)
        if gap < 1e-6:
            raise LightstageError("light basis: two basis lights have the same direction")
        tri, rim = triangulate(d)
        return cls(d, tri, rim)

    def weights(self, directions: np.ndarray, chunk: int = 4096) -> np.ndarray:
        """(N, L) interpolation weights of unit query directions (N, 3): three non-negative barycentric
        weights summing to 1 per row (two on the rim, one at or beyond a corner)."""
        q = np.asarray(directions, np.float64).reshape(-1, 3)
        q = q / np.maximum(np.linalg.norm(q, axis=1, keepdims=True), 1e-300)
        out = np.zeros((len(q), len(self)), np.float64)
        for i in range(0, len(q), chunk):
            out[i : i + chunk] = self._weights_chunk(q[i : i + chunk])
        return out

    def _weights_chunk(self, q: np.ndarray) -> np.ndarray:
        n, d = len(q), self.directions
        out = np.zeros((n, len(self)), np.float64)
        done = np.zeros(n, bool)
        if len(self.triangles):
            inv = _facet_inverses(d, self.triangles)  # (T, 3, 3)
            lam = np.einsum("tij,nj->nti", inv, q)  # (N, T, 3) coordinates in each facet's corner basis
            total = lam.sum(-1)
            with np.errstate(divide="ignore", invalid="ignore"):
                bary = np.where(total[..., None] > 0, lam / total[..., None], -np.inf)
            score = bary.min(-1)  # the facet the ray passes through has all coordinates >= 0
            best = np.argmax(score, axis=1)
            hit = score[np.arange(n), best] >= -COVER_EPS
            b = np.clip(bary[np.arange(n), best], 0.0, None)
            b /= b.sum(-1, keepdims=True)
            rows = np.flatnonzero(hit)
            for k in range(3):
                np.add.at(out, (rows, self.triangles[best[hit], k]), b[hit, k])
            done = hit
        if not np.all(done):
            rest = np.flatnonzero(~done)
            out[rest] = _rim_weights(q[rest], d, self.rim, len(self))
        return out

    def point_weights(self, direction: np.ndarray, intensity: float = 1.0) -> np.ndarray:
        """(L, 3) weights of one white point light from `direction`, `intensity` times a capture light."""
        w = self.weights(np.asarray(direction, np.float64).reshape(1, 3))[0] * float(intensity)
        return np.repeat(w[:, None], 3, axis=1)


def _min_angle(d: np.ndarray) -> float:
    """Smallest angle (radians) between two of the directions (inf for one)."""
    if len(d) < 2:
        return float("inf")
    dots = np.clip(d @ d.T, -1.0, 1.0)
    np.fill_diagonal(dots, -1.0)
    return float(np.arccos(dots.max()))


def triangulate(d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(triangles (T, 3), rim edges (E, 2)) of unit directions: the facets of the hull of the directions and
    the centre that do not touch the centre. When the centre is inside the directions' hull these are all of
    its facets (the sphere is covered, no rim); otherwise the facets that face away from the centre, i.e. the
    ones a ray from the centre leaves through, and the rim is their outer border."""
    from scipy.spatial import ConvexHull, QhullError

    if len(d) < 3:
        rim = np.array([[0, 1]]) if len(d) == 2 else np.zeros((0, 2), int)
        return np.zeros((0, 3), int), rim
    pts = np.vstack([d, np.zeros((1, 3))])
    try:
        hull = ConvexHull(pts)
    except QhullError:
        raise LightstageError(
            "light basis: the basis light directions lie in one plane through the centre (a single great "
            "circle); they cannot be triangulated"
        ) from None
    centre = len(d)
    tri = np.array([s for s in hull.simplices if centre not in s], int).reshape(-1, 3)
    edges: dict[tuple[int, int], int] = {}
    for t in tri:
        for a, b in ((t[0], t[1]), (t[1], t[2]), (t[2], t[0])):
            key = (min(a, b), max(a, b))
            edges[key] = edges.get(key, 0) + 1
    rim = np.array([e for e, count in edges.items() if count == 1], int).reshape(-1, 2)
    return tri, rim


def _facet_inverses(d: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """(T, 3, 3) inverses of the matrices whose columns are each facet's corner directions."""
    m = np.stack([d[triangles[:, 0]], d[triangles[:, 1]], d[triangles[:, 2]]], axis=-1)
    return np.linalg.inv(m)


def _rim_weights(q: np.ndarray, d: np.ndarray, rim: np.ndarray, count: int) -> np.ndarray:
    """Weights of directions outside the triangulated region: the nearest point (by angle) on a rim edge's
    great-circle arc, as two weights on its ends (one at a corner); the nearest light without a rim."""
    out = np.zeros((len(q), count), np.float64)
    if len(rim) == 0:
        out[np.arange(len(q)), np.argmax(q @ d.T, axis=1)] = 1.0
        return out
    a, b = d[rim[:, 0]], d[rim[:, 1]]  # (E, 3)
    # coordinates of q's projection onto each edge's plane in the (a, b) basis: solve the 2x2 Gram system
    ab = np.sum(a * b, -1)
    det = 1.0 - ab**2
    qa, qb = q @ a.T, q @ b.T  # (N, E)
    alpha = (qa - ab * qb) / det
    beta = (qb - ab * qa) / det
    alpha, beta = np.clip(alpha, 0.0, None), np.clip(beta, 0.0, None)
    zero = (alpha + beta) <= 0
    alpha = np.where(zero, np.where(qa >= qb, 1.0, 0.0), alpha)
    beta = np.where(zero, 1.0 - alpha, beta)
    s = alpha + beta
    alpha, beta = alpha / s, beta / s
    p = alpha[..., None] * a[None] + beta[..., None] * b[None]  # (N, E, 3) points on the chords
    cos = np.einsum("nek,nk->ne", p, q) / np.linalg.norm(p, axis=-1)
    e = np.argmax(cos, axis=1)
    rows = np.arange(len(q))
    np.add.at(out, (rows, rim[e, 0]), alpha[rows, e])
    np.add.at(out, (rows, rim[e, 1]), beta[rows, e])
    return out


def envmap_weights(env: EnvMap, basis: LightBasis, olat_factor: float) -> np.ndarray:
    """(L, 3) weights of an environment map (its rotation applied): each pixel's RGB energy L x Omega, spread
    over the basis lights by the point-light weights of its centre direction, times d^2 / I."""
    lights = all_pixel_lights(env)
    return float(olat_factor) * (basis.weights(lights.directions).T @ lights.rgb)


def rotation_table(env: EnvMap, basis: LightBasis, olat_factor: float, steps: int = 360) -> np.ndarray:
    """(steps, L, 3) `envmap_weights` of the map turned by 360 k / steps degrees about +z (k = 0 .. steps-1),
    on top of its own rotation: the viewer looks rotations up here instead of recomputing them. A turn about
    +z only shifts longitudes, so the weights are computed once per distinct (row, longitude) and gathered."""
    from lightstage.training.envmap import column_longitudes, direction_from_latlong, row_latitudes

    h, w = env.height, env.width
    turn = np.deg2rad(env.rotate_deg + 360.0 * np.arange(steps) / steps)
    lon = np.mod(column_longitudes(w)[:, None] + turn[None, :], 2 * np.pi)  # (W, steps)
    unique, inverse = np.unique(np.round(lon, 12), return_inverse=True)
    lat_g, lon_g = np.meshgrid(row_latitudes(h), unique, indexing="ij")
    wts = basis.weights(direction_from_latlong(lat_g, lon_g).reshape(-1, 3)).reshape(h, len(unique), -1)
    energy = env.energies()  # (H, W, 3)
    out = np.empty((steps, len(basis), 3))
    idx = inverse.reshape(w, steps)
    for k in range(steps):
        out[k] = np.einsum("hwl,hwc->lc", wts[:, idx[:, k]], energy)
    return float(olat_factor) * out


def relight_basis(images: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """(H, W, 3) float32: sum over l of weights[l] (RGB) times basis image images[l] (L, H, W, 3)."""
    imgs = np.asarray(images)
    w = np.asarray(weights, np.float64).reshape(len(imgs), 3)
    return np.einsum("lhwc,lc->hwc", imgs.astype(np.float64, copy=False), w).astype(np.float32)


def stage_directions(light_directions: dict[str, np.ndarray], count: int) -> np.ndarray:
    """Up to `count` unit directions spread over a capture's stage lights (the union over groups of the
    calibrated light directions, which the rig's rotation spreads over the sphere): farthest-point sampling
    from the highest light, deterministic."""
    d = np.concatenate(
        [np.asarray(v, np.float64).reshape(-1, 3) for _, v in sorted(light_directions.items())]
    )
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    d = _dedupe(d)
    return d if count >= len(d) else d[farthest_points(d, count)]


def farthest_points(d: np.ndarray, count: int) -> list[int]:
    """Indices of `count` unit directions spread over `d`: farthest-point sampling from the highest one."""
    chosen = [int(np.argmax(d[:, 2]))]
    dist = 1.0 - d @ d[chosen[0]]
    for _ in range(min(count, len(d)) - 1):
        k = int(np.argmax(dist))
        chosen.append(k)
        dist = np.minimum(dist, 1.0 - d @ d[k])
    return chosen


def _dedupe(d: np.ndarray, tol: float = 1e-6) -> np.ndarray:
    """The directions without repeats (first occurrence kept)."""
    keep: list[int] = []
    for i in range(len(d)):
        if not keep or np.max(d[keep] @ d[i]) < 1.0 - tol:
            keep.append(i)
    return d[keep]


def sphere_directions(count: int, min_elevation_deg: float = -40.0) -> np.ndarray:
    """`count` unit directions spread evenly (a Fibonacci spiral) over the sphere above `min_elevation_deg`
    (a bottom-truncated stage) for a model without a calibration."""
    if count < 1:
        raise LightstageError(f"basis light count must be >= 1, got {count}")
    z_min = np.sin(np.deg2rad(min_elevation_deg))
    k = np.arange(count) + 0.5
    z = 1.0 - (1.0 - z_min) * k / count
    phi = k * np.pi * (3.0 - np.sqrt(5.0))
    r = np.sqrt(np.clip(1.0 - z**2, 0.0, None))
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


STAGE_BASIS_LIGHTS = 64  # basis lights of the viewer's model source and of `relight --lights stage`


def stage_basis(calibration, count: int = STAGE_BASIS_LIGHTS) -> LightBasis:
    """The model basis: `count` of the calibrated stage lights' directions over all groups (`stage_directions`),
    or an even spread over a bottom-truncated sphere when there is no calibration."""
    if calibration is not None and calibration.light_positions:
        dirs = {g: calibration.light_directions(g) for g in calibration.light_positions}
        return LightBasis.of(stage_directions(dirs, count))
    return LightBasis.of(sphere_directions(count))


def stage_lights(env: EnvMap, basis: LightBasis) -> Lights:
    """The envmap as lights at the basis directions carrying `envmap_weights` (irradiance units, factor 1):
    `relight_image` of these is the image the viewer shows for the map (one definition of the weights)."""
    return Lights(basis.directions.copy(), envmap_weights(env, basis, 1.0))
