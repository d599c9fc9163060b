"""Per-view compression of an OLAT basis: the light-transport matrix (pixels x lights) is close to low rank, so a
truncated SVD keeps the fewest components whose relative Frobenius error meets a stated tolerance. Components
are stored in half precision (each scaled to a peak of 1) and the coefficients refitted to the rounded
components, so the error reported is the one the viewer shows."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lightstage.errors import LightstageError
from lightstage.viewer.display import component_cap


@dataclass(frozen=True)
class CompressedBasis:
    """basis[l] ~= sum_j coefficients[j, l] * components[j] inside `crop` (zero outside it).

    components: (k, h, w, 3) float16 images of the crop; coefficients: (k, L) float32; crop: (x0, y0, w, h) in
    the full (height, width) frame; relative_error: ||basis - reconstruction||_F / ||basis||_F (linear HDR)."""

    components: np.ndarray
    coefficients: np.ndarray
    crop: tuple[int, int, int, int]
    height: int
    width: int
    relative_error: float

    @property
    def rank(self) -> int:
        return int(self.components.shape[0])

    def reconstruct(self, weights: np.ndarray | None = None) -> np.ndarray:
        """(L, H, W, 3) float32 basis images back (or, with (L, 3) RGB `weights`, the one relit image)."""
        x0, y0, w, h = self.crop
        comp = self.components.astype(np.float64).reshape(self.rank, -1)
        if weights is None:
            out = np.zeros((self.coefficients.shape[1], self.height, self.width, 3), np.float32)
            out[:, y0 : y0 + h, x0 : x0 + w] = (self.coefficients.T.astype(np.float64) @ comp).reshape(
                -1, h, w, 3
            )
            return out
        coef = self.coefficients.astype(np.float64) @ np.asarray(weights, np.float64)  # (k, 3)
        img = np.einsum("kpc,kc->pc", comp.reshape(self.rank, -1, 3), coef).reshape(h, w, 3)
        out = np.zeros((self.height, self.width, 3), np.float32)
        out[y0 : y0 + h, x0 : x0 + w] = img
        return out


def content_crop(images: np.ndarray, margin: int = 1) -> tuple[int, int, int, int]:
    """(x0, y0, w, h): the smallest box holding every non-zero pixel of any image (plus `margin`), or the whole
    frame. A model's renders are exactly zero where no ray meets the object, so most of the frame drops."""
    nonzero = np.any(np.asarray(images) != 0, axis=(0, 3))
    height, width = nonzero.shape
    if not nonzero.any():
        return 0, 0, 1, 1
    rows, cols = np.flatnonzero(nonzero.any(1)), np.flatnonzero(nonzero.any(0))
    y0, y1 = max(0, rows[0] - margin), min(height, rows[-1] + 1 + margin)
    x0, x1 = max(0, cols[0] - margin), min(width, cols[-1] + 1 + margin)
    return int(x0), int(y0), int(x1 - x0), int(y1 - y0)


def rank_for(singular_values: np.ndarray, tolerance: float) -> int:
    """Fewest leading components whose discarded energy sqrt(sum s_j^2, j >= k) / ||s|| is <= tolerance."""
    s2 = np.asarray(singular_values, np.float64) ** 2
    total = s2.sum()
    if total <= 0:
        return 1
    tail = np.sqrt(np.concatenate([np.cumsum(s2[::-1])[::-1], [0.0]]) / total)  # tail[k]: error keeping k
    return max(1, int(np.argmax(tail <= tolerance)))


def compress_basis(
    images: np.ndarray,
    tolerance: float = 0.02,
    max_components: int = 64,
    crop: bool = True,
    max_bytes: int | None = None,
) -> CompressedBasis:
    """Compress (L, H, W, 3) linear HDR basis images to the fewest SVD components meeting `tolerance` (relative
    Frobenius error, half rounding included; more are added when rounding pushes it over), at most
    `max_components` and at most `max_bytes` of half-float components of the crop (then the error is what that
    many give)."""
    imgs = np.asarray(images, np.float32)
    if imgs.ndim != 4 or imgs.shape[-1] != 3 or len(imgs) == 0:
        raise LightstageError(f"basis images must be (L, H, W, 3), got {imgs.shape}")
    if not tolerance >= 0 or max_components < 1:
        raise LightstageError(f"compression: tolerance must be >= 0 and max components >= 1, got {tolerance}")
    L, H, W, _ = imgs.shape
    x0, y0, w, h = content_crop(imgs) if crop else (0, 0, W, H)
    m = imgs[:, y0 : y0 + h, x0 : x0 + w].reshape(L, -1).astype(np.float64)  # lights x (pixels * 3)
    norm = float(np.linalg.norm(m))
    s, vecs = _singular(m)
    limit = min(max_components, int(np.count_nonzero(s > s[0] * 1e-7)) if s[0] > 0 else 1)
    if max_bytes is not None:
        limit = min(limit, component_cap(max_bytes, w, h, f"a {W}x{H} view"))
    k = min(rank_for(s, tolerance), limit)
    while True:
        comp, coef, err = _fit(m, (vecs[:, :k].T @ m) / np.maximum(s[:k, None], 1e-300), norm)
        if err <= tolerance or k >= limit:
            break
        k += 1
    return CompressedBasis(comp.reshape(k, h, w, 3), coef, (x0, y0, w, h), H, W, err)


def _singular(m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Singular values (descending) and left singular vectors of a wide lights x values matrix, from its small
    L x L Gram matrix (several times cheaper than an SVD of the wide matrix; the components kept lie far
    above the precision the squaring costs)."""
    evals, evecs = np.linalg.eigh(m @ m.T)
    order = np.argsort(evals)[::-1]
    return np.sqrt(np.clip(evals[order], 0.0, None)), evecs[:, order]


def _fit(m: np.ndarray, rows: np.ndarray, norm: float) -> tuple[np.ndarray, np.ndarray, float]:
    """Half components (each scaled to peak 1), least-squares coefficients for them, relative error."""
    peak = np.maximum(np.abs(rows).max(axis=1, keepdims=True), 1e-300)
    comp = (rows / peak).astype(np.float16)
    c = comp.astype(np.float64)
    coef = np.linalg.solve(c @ c.T, c @ m.T)  # (k, L) least squares: m ~= coef.T @ c (normal equations)
    coef32 = coef.astype(np.float32)
    resid = m - coef32.astype(np.float64).T @ c
    err = float(np.linalg.norm(resid) / norm) if norm > 0 else 0.0
    return comp, coef32, err
