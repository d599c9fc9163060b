"""The sets of a viewer bundle (one per source: the capture's frames, a trained model's renders) and the
envmaps' weight tables. Each writes its binary files into the bundle folder and returns its manifest entry."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from lightstage.training.light_basis import LightBasis
from lightstage.viewer.compress import CompressedBasis, compress_basis
from lightstage.viewer.display import Budget, display_camera
from lightstage.viewer.sources import RingView

ROTATION_STEPS = 360  # rows of an envmap weight table: one per degree
DEFAULT_AZIMUTH_DEG = 45.0  # the page's initial point light (and lightstage.viewer.reference's)
DEFAULT_ELEVATION_DEG = 30.0


def azel_direction(azimuth_deg: float, elevation_deg: float) -> np.ndarray:
    """Unit direction from azimuth (from +x towards +y) and elevation in degrees (the `azel:` light spec)."""
    az, el = np.deg2rad(azimuth_deg), np.deg2rad(elevation_deg)
    return np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])


def _write(path: Path, array: np.ndarray) -> None:
    """Little-endian raw array (the page reads it with a typed array)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(np.ascontiguousarray(array).astype(array.dtype.newbyteorder("<"), copy=False).tobytes())


def basis_entry(basis: LightBasis, **extra: Any) -> dict[str, Any]:
    """Manifest entry of a light basis: directions, triangles and rim edges (the page's point-light weights)."""
    return {
        "lights": len(basis),
        "directions": basis.directions.tolist(),
        "triangles": basis.triangles.tolist(),
        "rim": basis.rim.tolist(),
        **extra,
    }


def view_entry(rv: RingView, comp: CompressedBasis, basis: int, file: str, **extra: Any) -> dict[str, Any]:
    """Manifest entry of one view: size, crop, components file and coefficients (float32 values)."""
    return {
        "name": rv.name,
        "label": rv.label,
        "view_id": str(rv.view) if rv.view is not None else None,
        "width": comp.width,
        "height": comp.height,
        "crop": list(comp.crop),
        "components": comp.rank,
        "relative_error": round(comp.relative_error, 6),
        "file": file,
        "coefficients": [float(v) for v in comp.coefficients.reshape(-1)],
        "basis": basis,
        "ab": None,  # the capture set's view of the same id, when built (build._link_ab)
        **extra,
    }


def _exposure(comp: CompressedBasis, weights: np.ndarray) -> float:
    """The page's default exposure for these weights: auto exposure (99th percentile) of the first view."""
    from lightstage.tonemap import auto_exposure

    return float(auto_exposure(comp.reconstruct(weights), 99.0))


def capture_set(work, scene, config, bundle: Path, progress: bool, budget: Budget) -> dict[str, Any]:
    """The captured OLAT frames of the ring's calibrated views at the display size, compressed per view within
    the view's share of the byte `budget`; one light basis per group (the lights turn with the rig)."""
    from tqdm import tqdm

    from lightstage.viewer.sources import calibrated_ring, capture_basis, ring_camera, ring_groups

    calib = scene.calibration
    camera = ring_camera(calib, config.camera)
    ring = calibrated_ring(calib, camera, ring_groups(calib, camera, config.views))
    bases: list[LightBasis] = []
    keys: list[tuple] = []
    entries: list[dict[str, Any]] = []
    views, first = [], None
    for rv in tqdm(ring, desc="viewer: capture basis", unit="view", disable=not progress, leave=False):
        dirs, frames, lights = capture_basis(
            work, calib, rv.view, config.capture_lights or None, display=config.display_size
        )
        key = (rv.view.group, tuple(lights))
        if key not in keys:
            keys.append(key)
            bases.append(LightBasis.of(dirs))
            entries.append(basis_entry(bases[-1], group=rv.view.group, light_indices=lights))
        comp = compress_basis(
            frames, config.tolerance, config.max_components, crop=False, max_bytes=budget.share()
        )
        budget.spend(comp.components.nbytes)
        del frames
        file = f"data/capture/{rv.name}.bin"
        _write(bundle / file, comp.components)
        views.append(view_entry(rv, comp, keys.index(key), file))
        first = first or (comp, keys.index(key))
    direction = azel_direction(DEFAULT_AZIMUTH_DEG, DEFAULT_ELEVATION_DEG)
    return {
        "name": "capture",
        "source": "capture",
        "description": f"captured OLAT frames (processed), camera {camera}, {len(ring)} view(s)",
        "basis_lights": max(len(b) for b in bases),
        "bases": entries,
        "views": views,
        "exposure": _exposure(first[0], bases[first[1]].point_weights(direction)),
        "_bases": bases,
    }


def model_set(
    work, scene, config, bundle: Path, progress: bool, budget: Budget, model: Any = None
) -> dict[str, Any]:
    """A trained model's OLAT renders under `config.basis_lights` stage lights for the ring (calibrated views
    plus novel ones, or an orbit without a calibration) at the display size, one density pass per view,
    compressed per view within the view's share of the byte `budget`."""
    from tqdm import tqdm

    from lightstage.training.envmap import parse_resolution
    from lightstage.training.inference import load_trained
    from lightstage.training.light_basis import stage_basis
    from lightstage.training.olat_basis import render_olat_basis
    from lightstage.viewer.sources import (
        calibrated_ring,
        check_basis_size,
        novel_ring,
        orbit_ring,
        ring_camera,
        ring_groups,
    )

    if model is None:
        model = load_trained(work, config.checkpoint, config.device)
    calib = scene.calibration
    if calib is not None:
        camera = ring_camera(calib, config.camera)
        ring = novel_ring(
            calib, calibrated_ring(calib, camera, ring_groups(calib, camera, config.views)), config.novel
        )
        where = f"camera {camera}, {len(ring)} view(s), {sum(v.view is None for v in ring)} of them novel"
    else:
        ring = orbit_ring(model, config.orbit_views, parse_resolution(config.orbit_size))
        where = f"{len(ring)} orbit view(s) (no calibration)"
    basis = stage_basis(calib, config.basis_lights)
    views, first = [], None
    bar = tqdm(
        total=float(len(ring)), desc="viewer: model basis", unit="view", disable=not progress, leave=False
    )
    bar.bar_format = "{l_bar}{bar}| {n:.1f}/{total:.0f} views [{elapsed}<{remaining}]"
    for rv in ring:
        rv = replace(rv, camera=display_camera(rv.camera, config.display_size))
        rays, done = rv.camera.width * rv.camera.height, [0]

        def tick(n: int, rays=rays, done=done) -> None:
            bar.update((n - done[0]) / rays)
            done[0] = n

        check_basis_size(len(basis), rv.camera.width, rv.camera.height, f"view {rv.label}")
        images = render_olat_basis(model, rv.camera, basis.directions, on_chunk=tick)
        comp = compress_basis(
            images, config.tolerance, config.max_components, crop=True, max_bytes=budget.share()
        )
        budget.spend(comp.components.nbytes)
        del images
        file = f"data/model/{rv.name}.bin"
        _write(bundle / file, comp.components)
        views.append(view_entry(rv, comp, 0, file))
        first = first or comp
    bar.close()
    step = getattr(model, "step", None)
    direction = azel_direction(DEFAULT_AZIMUTH_DEG, DEFAULT_ELEVATION_DEG)
    return {
        "name": "model",
        "source": "model",
        "description": f"trained model{f' (step {step})' if step else ''}: renders under {len(basis)} stage "
        f"lights, {where}",
        "basis_lights": len(basis),
        "bases": [basis_entry(basis)],
        "views": views,
        "exposure": _exposure(first, basis.point_weights(direction)),
        "_bases": [basis],
    }


def write_envmaps(envmaps, sets: list[dict[str, Any]], olat_factor: float, bundle: Path, progress: bool):
    """Per envmap: its radiance (float32) and preview PNG, and per set and basis the (360, L, 3) float32 table
    of `rotation_table` weights; returns the manifest entries (with each set's default envmap exposure)."""
    from tqdm import tqdm

    from lightstage.frames import write_image
    from lightstage.tonemap import auto_exposure, tonemap_u8
    from lightstage.training.envmap import resample
    from lightstage.training.light_basis import rotation_table

    out = []
    jobs = [(n, e) for n, e in envmaps]
    for name, env in tqdm(jobs, desc="viewer: envmap weights", unit="map", disable=not progress, leave=False):
        _write(bundle / "env" / f"{name}.bin", np.asarray(env.radiance, np.float32))
        big = resample(env.radiance, 256, 128)
        write_image(bundle / "env" / f"{name}.png", tonemap_u8(big, auto_exposure(big, 95.0)))
        entry: dict[str, Any] = {
            "name": name,
            "width": env.width,
            "height": env.height,
            "radiance": f"env/{name}.bin",
            "preview": f"env/{name}.png",
            "tables": {},
            "exposure": {},
        }
        for s in sets:
            files = []
            for b, basis in enumerate(s["_bases"]):
                table = rotation_table(env, basis, olat_factor, ROTATION_STEPS).astype(np.float32)
                file = f"data/{s['name']}/basis{b}_{name}.bin"
                _write(bundle / file, table)
                files.append(file)
                if b == s["views"][0]["basis"]:
                    first = _compressed(bundle, s["views"][0])
                    entry["exposure"][s["name"]] = _exposure(first, table[0])
            entry["tables"][s["name"]] = files
        out.append(entry)
    return out


def _compressed(bundle: Path, view: dict[str, Any]) -> CompressedBasis:
    """A view's compressed basis read back from the bundle (what the page gets)."""
    x0, y0, w, h = view["crop"]
    k = view["components"]
    comp = np.fromfile(bundle / view["file"], dtype="<f2").reshape(k, h, w, 3)
    coef = np.asarray(view["coefficients"], np.float32).reshape(k, -1)
    return CompressedBasis(comp, coef, (x0, y0, w, h), view["height"], view["width"], view["relative_error"])
