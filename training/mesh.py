"""Meshes from a trained model's density (`lightstage mesh`): density on an N^3 grid over the normalised scene
bounds [-1, 1]^3 (queried in chunks, on the GPU when present), marching cubes (scikit-image) at a density
level, vertices in world units (metres), binary PLY output.

The level (`surface_level`, used unless `threshold` is given) comes from the transmittance the field implies,
so it needs no constant tuned on one model's density scale: along every grid line through the bounds, in both
directions of all three axes (6 N^2 rays entering at a face of the cube), the optical depth
tau = integral of sigma ds (trapezoid rule, s in the model's normalised units, the ones sigma is trained in)
is accumulated from the entry face; the ray's median-depth point is where tau first reaches ln 2, i.e. where its
transmittance falls to 1/2 and half of an opaque ray's weight lies in front. The level is the median, over all
rays that get there, of the density at that point. Marching cubes at that level therefore puts the surface where
the renderer's rays see it (for a sharp field any level up the density edge gives the same surface; for a soft,
barely trained one the level adapts to its scale), it does not move with `resolution` beyond discretisation, and
it always lies inside the grid's density range. A field with no such ray (transparent everywhere) has no surface
by this rule: that is an error naming the density range, and `threshold` chooses a level by hand.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from lightstage.config import load
from lightstage.errors import LightstageError
from lightstage.workdir import WorkDir

if TYPE_CHECKING:
    from lightstage.training.inference import RelightableModel


@dataclass
class MeshConfig:
    """Options of `lightstage mesh`."""

    resolution: int = 256  # grid points per axis over [-1, 1]^3
    threshold: float | None = None  # density level (the model's units); None: `surface_level` of the field
    chunk: int = 262144  # points per density query
    checkpoint: str | None = None
    device: str = "auto"  # "auto": cuda when available, else cpu
    out: str = "mesh.ply"  # only .ply is written

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> MeshConfig:
        """The strict loader (`lightstage.config`): unknown keys and wrong types name the key."""
        return load(cls, d)


def pick_device(device: str) -> str:
    """'auto' -> 'cuda' when torch sees a GPU, else 'cpu'; anything else unchanged."""
    if device != "auto":
        return device
    import torch

    return "cuda" if torch.cuda.is_available() else "cpu"


def bounds_of(model: RelightableModel) -> tuple[np.ndarray, np.ndarray]:
    """(centre (3,), half-extent (3,)) of the model's normalised bounds in world units."""
    centre = np.broadcast_to(np.asarray(model.centre, np.float64), (3,)).copy()
    scale = np.broadcast_to(np.asarray(model.scale, np.float64), (3,)).copy()
    if not np.all(scale > 0):
        raise LightstageError(f"model scene scale must be positive, got {scale}")
    return centre, scale


def density_grid(
    model: RelightableModel, resolution: int, chunk: int = 262144, device: str = "cpu", progress: bool = True
) -> np.ndarray:
    """(N, N, N) float32 density at world points centre + scale * x, x on an N-point grid over [-1, 1]^3
    (index order x, y, z); queried `chunk` points at a time, one z-slab batch after another."""
    import torch
    from tqdm import tqdm

    if resolution < 2:
        raise LightstageError(f"mesh resolution must be >= 2, got {resolution}")
    centre, scale = bounds_of(model)
    axes = [
        torch.linspace(-1.0, 1.0, resolution, dtype=torch.float64) * s + c
        for c, s in zip(centre, scale, strict=True)
    ]
    out = np.empty((resolution,) * 3, np.float32)
    total = resolution**3
    flat = out.reshape(-1)
    chunk = max(1, int(chunk))
    n2 = resolution * resolution
    with (
        torch.no_grad(),
        tqdm(total=total, desc="density", unit="pt", unit_scale=True, disable=not progress) as bar,
    ):
        for start in range(0, total, chunk):
            idx = torch.arange(start, min(start + chunk, total), dtype=torch.int64)
            pts = torch.stack(
                [axes[0][idx // n2], axes[1][(idx // resolution) % resolution], axes[2][idx % resolution]], 1
            )
            sigma = model.density(pts.to(device=device, dtype=torch.float32))
            sigma = torch.as_tensor(sigma).reshape(-1)
            if sigma.shape[0] != idx.shape[0]:
                raise LightstageError(
                    f"model.density returned {sigma.shape[0]} values for {idx.shape[0]} points"
                )
            flat[start : start + idx.shape[0]] = sigma.detach().float().cpu().numpy()
            bar.update(idx.shape[0])
    return out


MESH_SUFFIXES = (".ply",)


def check_out_path(out: str | Path) -> Path:
    """`out` as a Path when its extension is one this module writes (.ply), else a LightstageError."""
    path = Path(out)
    if path.suffix.lower() not in MESH_SUFFIXES:
        raise LightstageError(
            f"{path}: cannot write a {path.suffix or 'extension-less'} mesh; "
            f"--out must end in {' or '.join(MESH_SUFFIXES)} (binary PLY)"
        )
    return path


def surface_level(grid: np.ndarray) -> dict[str, Any]:
    """The density level of the field's median-depth surface (module docstring): {'level', 'rays' (that reach
    transmittance 1/2), 'rays_total'}. `grid` spans [-1, 1] per axis in the model's normalised units."""
    grid = np.nan_to_num(np.asarray(grid, np.float32), nan=0.0, posinf=np.float32(3e38))
    lo, hi = float(grid.min()), float(grid.max())
    ln2 = math.log(2.0)
    values: list[np.ndarray] = []
    total, peak = 0, 0.0
    for axis in range(3):
        g = np.moveaxis(grid, axis, -1)
        step = 2.0 / (g.shape[-1] - 1)
        for line in (g, g[..., ::-1]):
            tau = np.zeros(line.shape, np.float32)
            np.cumsum((line[..., 1:] + line[..., :-1]) * np.float32(0.5 * step), axis=-1, out=tau[..., 1:])
            total += tau[..., 0].size
            peak = max(peak, float(tau[..., -1].max()))
            reached = tau[..., -1] >= ln2
            if not reached.any():
                continue
            t, s = tau[reached], line[reached]
            k = np.argmax(t >= ln2, axis=-1)[:, None]  # >= 1: tau starts at 0
            t0, t1 = np.take_along_axis(t, k - 1, -1)[:, 0], np.take_along_axis(t, k, -1)[:, 0]
            s0, s1 = np.take_along_axis(s, k - 1, -1)[:, 0], np.take_along_axis(s, k, -1)[:, 0]
            f = (ln2 - t0) / np.maximum(t1 - t0, np.float32(1e-30))
            values.append(s0 + f * (s1 - s0))
    if not values:
        raise LightstageError(
            f"the field is transparent along every grid line through the bounds (largest optical depth "
            f"{peak:.3g} < ln 2): no surface at transmittance 1/2; choose --threshold inside its density range "
            f"[{lo:g}, {hi:g}]"
        )
    v = np.concatenate(values)
    level = float(np.median(v))
    # a plateau (e.g. a binary field) can put the median on the range's end: any level on its edge is the same
    # surface, so keep it strictly inside for marching cubes
    margin = 1e-3 * (hi - lo)
    level = min(max(level, lo + margin), hi - margin)
    return {"level": level, "rays": int(v.size), "rays_total": int(total)}


def extract_mesh(
    grid: np.ndarray, threshold: float, centre: np.ndarray, scale: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Marching cubes of a density grid over centre +- scale: (vertices (V, 3) world units, faces (F, 3)
    counter-clockwise seen from outside, outward normals (V, 3))."""
    from skimage.measure import marching_cubes

    grid = np.nan_to_num(np.asarray(grid, np.float32), nan=0.0, posinf=np.float32(3e38))
    lo, hi = float(grid.min()), float(grid.max())
    if not lo < threshold < hi:
        raise LightstageError(
            f"density threshold {threshold:g} is outside the grid's range [{lo:g}, {hi:g}]: no surface "
            "(choose --threshold inside it)"
        )
    n = np.asarray(grid.shape, np.float64)
    spacing = 2.0 * np.asarray(scale, np.float64) / (n - 1)
    verts, faces, normals, _ = marching_cubes(
        grid, level=threshold, spacing=tuple(spacing), gradient_direction="descent"
    )
    verts = verts + (np.asarray(centre, np.float64) - np.asarray(scale, np.float64))
    # scikit-image winds triangles clockwise seen from outside here; flip to counter-clockwise (front faces out)
    faces = faces[:, [0, 2, 1]]
    return verts.astype(np.float64), np.ascontiguousarray(faces, dtype=np.int32), normals.astype(np.float32)


def write_ply(
    path: str | Path, vertices: np.ndarray, faces: np.ndarray, normals: np.ndarray | None = None
) -> None:
    """Binary little-endian PLY with float32 x y z (+ nx ny nz) and int32 triangle lists, written atomically."""
    from lightstage.atomic import atomic_path

    v = np.asarray(vertices, np.float32)
    props = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    if normals is not None:
        props += [("nx", "<f4"), ("ny", "<f4"), ("nz", "<f4")]
    vrec = np.empty(len(v), dtype=props)
    vrec["x"], vrec["y"], vrec["z"] = v[:, 0], v[:, 1], v[:, 2]
    if normals is not None:
        nrm = np.asarray(normals, np.float32)
        vrec["nx"], vrec["ny"], vrec["nz"] = nrm[:, 0], nrm[:, 1], nrm[:, 2]
    frec = np.empty(len(faces), dtype=[("n", "u1"), ("v", "<i4", (3,))])
    frec["n"] = 3
    frec["v"] = np.asarray(faces, np.int32)
    header = ["ply", "format binary_little_endian 1.0", "comment lightstage mesh, world units (metres)"]
    header.append(f"element vertex {len(v)}")
    header += [f"property float {name}" for name, _ in props]
    header += [f"element face {len(frec)}", "property list uchar int vertex_indices", "end_header"]
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        f.write(("\n".join(header) + "\n").encode("ascii"))
        f.write(vrec.tobytes())
        f.write(frec.tobytes())


def read_ply(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Read back a PLY written by `write_ply`: (vertices (V, 3) float32, faces (F, 3) int32)."""
    data = Path(path).read_bytes()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    lines = data[:end].decode("ascii").splitlines()
    nv = int(next(ln for ln in lines if ln.startswith("element vertex")).split()[-1])
    nf = int(next(ln for ln in lines if ln.startswith("element face")).split()[-1])
    nprops = sum(1 for ln in lines if ln.startswith("property float"))
    verts = np.frombuffer(data, "<f4", nv * nprops, end).reshape(nv, nprops)[:, :3]
    frec = np.frombuffer(data, [("n", "u1"), ("v", "<i4", (3,))], nf, end + nv * nprops * 4)
    return verts.copy(), frec["v"].copy()


def run_mesh(
    work: WorkDir,
    config: MeshConfig,
    progress: bool = True,
    model: RelightableModel | None = None,
) -> dict[str, Any]:
    """Density grid -> marching cubes -> PLY at config.out; a JSON summary beside it (FILE.json)."""
    from lightstage.atomic import write_json_atomic

    out = check_out_path(config.out)  # before any work
    if config.threshold is not None and not float(config.threshold) > 0:  # also refuses NaN
        raise LightstageError(
            f"density threshold {config.threshold:g}: the density is never negative, so a surface needs a "
            "level > 0 (leave --threshold out to take it from the field's transmittance)"
        )
    t0 = time.perf_counter()
    device = pick_device(config.device)
    if model is None:
        from lightstage.training.inference import load_trained

        model = load_trained(work, config.checkpoint, device)
    centre, scale = bounds_of(model)
    grid = density_grid(model, config.resolution, config.chunk, device, progress)
    t1 = time.perf_counter()
    if config.threshold is None:
        auto = surface_level(grid)
        threshold = auto["level"]
        rule = (
            f"median density where rays through the grid reach transmittance 1/2 "
            f"({auto['rays']} of {auto['rays_total']} axis rays)"
        )
    else:
        threshold, rule = float(config.threshold), "given"
    verts, faces, normals = extract_mesh(grid, threshold, centre, scale)
    t2 = time.perf_counter()
    write_ply(out, verts, faces, normals)
    summary = {
        "ply": str(out),
        "resolution": config.resolution,
        "threshold": threshold,
        "threshold_rule": rule,
        "device": device,
        "vertices": int(len(verts)),
        "faces": int(len(faces)),
        "bounds_centre": centre.tolist(),
        "bounds_scale": scale.tolist(),
        "mesh_min": verts.min(axis=0).tolist() if len(verts) else None,
        "mesh_max": verts.max(axis=0).tolist() if len(verts) else None,
        "density_range": [float(grid.min()), float(grid.max())],
        "seconds_density": round(t1 - t0, 3),
        "seconds_marching_cubes": round(t2 - t1, 3),
        "seconds": round(time.perf_counter() - t0, 3),
    }
    write_json_atomic(out.with_suffix(".json"), summary)
    return summary
