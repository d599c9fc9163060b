"""Mesh extraction: marching cubes of an analytic sphere density lands at the right radius in world units; the
default level comes from the field's transmittance (surface_level) and works on a trained checkpoint."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from lightstage.errors import LightstageError
from lightstage.training.mesh import (
    MeshConfig,
    density_grid,
    extract_mesh,
    read_ply,
    run_mesh,
    surface_level,
    write_ply,
)
from lightstage.workdir import WorkDir


class SphereDensity:
    """Density model: 100 inside a ball of `radius` (world units) at `centre`, 0 outside, smooth 1 mm edge.
    Bounds are deliberately off-centre and anisotropic so the normalised-to-world mapping is exercised."""

    def __init__(self, centre=(0.12, -0.3, 1.1), radius=0.15):
        self.sphere_centre = np.asarray(centre, np.float64)
        self.radius = radius
        self.centre = self.sphere_centre + np.array([0.02, -0.01, 0.03])
        self.scale = np.array([0.25, 0.3, 0.22])
        self.queries = 0

    def density(self, points_world):
        self.queries += 1
        p = torch.as_tensor(points_world, dtype=torch.float32)
        c = torch.as_tensor(self.sphere_centre, dtype=torch.float32, device=p.device)
        r = torch.linalg.norm(p - c, dim=-1)
        return 100.0 * torch.sigmoid((self.radius - r) / 0.001)

    def render_rays(self, origins, directions, light_directions, chunk=65536):
        raise NotImplementedError

    def image_from_camera(self, camera, light_direction):
        raise NotImplementedError


def test_grid_covers_the_normalised_bounds_in_world_units():
    model = SphereDensity()
    grid = density_grid(model, 9, chunk=100, progress=False)
    assert grid.shape == (9, 9, 9) and model.queries == 8  # 729 points in chunks of 100
    # the grid point nearest the sphere centre is inside, the corners outside
    lo = model.centre - model.scale
    idx = np.round((model.sphere_centre - lo) / (2 * model.scale) * 8).astype(int)
    assert grid[tuple(idx)] > 99 and grid[0, 0, 0] < 1


def test_marching_cubes_sphere_radius_in_world_units():
    model = SphereDensity()
    n = 64
    grid = density_grid(model, n, chunk=50000, progress=False)
    verts, faces, normals = extract_mesh(grid, 50.0, model.centre, model.scale)
    r = np.linalg.norm(verts - model.sphere_centre, axis=1)
    voxel = (2 * model.scale / (n - 1)).max()
    assert abs(r.mean() - model.radius) < 0.1 * voxel
    assert r.std() < 0.1 * voxel and np.abs(r - model.radius).max() < 0.5 * voxel
    assert np.allclose(verts.mean(axis=0), model.sphere_centre, atol=0.05 * voxel)
    # normals point outwards (density decreases outwards); the 1 mm edge makes gradients coarse at this grid
    outward = (verts - model.sphere_centre) / r[:, None]
    cos = np.sum(normals * outward, axis=1)
    assert cos.min() > 0.5 and np.median(cos) > 0.95
    assert faces.max() < len(verts)
    tri = verts[faces]
    face_normals = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    assert np.all(
        np.sum(face_normals * (tri.mean(axis=1) - model.sphere_centre), axis=1) > 0
    )  # CCW from outside
    # area of the surface ~ 4 pi r^2
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1).sum()
    assert area == pytest.approx(4 * np.pi * model.radius**2, rel=0.02)


def test_threshold_outside_the_density_range_is_an_error():
    grid = np.zeros((4, 4, 4), np.float32)
    with pytest.raises(LightstageError, match="outside"):
        extract_mesh(grid, 50.0, np.zeros(3), np.ones(3))


def test_ply_round_trip(tmp_path):
    verts = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1.5]], np.float64)
    faces = np.array([[0, 1, 2], [0, 1, 3]], np.int32)
    write_ply(tmp_path / "m.ply", verts, faces, np.ones((4, 3)))
    head = (tmp_path / "m.ply").read_bytes()[:300]
    assert head.startswith(b"ply\nformat binary_little_endian 1.0\n") and b"element face 2" in head
    v, f = read_ply(tmp_path / "m.ply")
    assert np.allclose(v, verts) and np.array_equal(f, faces)


def test_run_mesh_writes_ply_and_summary(tmp_path):
    model = SphereDensity()
    out = tmp_path / "mesh" / "sphere.ply"
    config = MeshConfig.from_dict({"resolution": 32, "threshold": 50.0, "device": "auto", "out": str(out)})
    summary = run_mesh(WorkDir.at(tmp_path), config, progress=False, model=model)
    v, f = read_ply(out)
    assert len(v) == summary["vertices"] > 100 and len(f) == summary["faces"]
    r = np.linalg.norm(v - model.sphere_centre, axis=1)
    assert abs(r.mean() - model.radius) < 0.01
    assert json.loads(out.with_suffix(".json").read_text())["threshold"] == 50.0
    with pytest.raises(LightstageError, match="resolution"):
        MeshConfig.from_dict({"resolution": "high"})
    with pytest.raises(LightstageError, match="resolution must be"):
        density_grid(model, 1)


class SoftBlob:
    """A smooth Gaussian-profile density (like a barely trained field): A exp(-(r / w)^2) about `centre`."""

    def __init__(self, amplitude=20.0, width=0.3):
        self.centre = np.array([0.0, 0.1, -0.2])
        self.scale = np.array([0.5, 0.5, 0.5])
        self.amplitude, self.width = amplitude, width

    def density(self, points_world):
        p = torch.as_tensor(points_world, dtype=torch.float32)
        r = torch.linalg.norm(p - torch.as_tensor(self.centre, dtype=torch.float32), dim=-1)
        return self.amplitude * torch.exp(-((r / self.width) ** 2))


def test_default_level_from_transmittance_on_a_sharp_sphere(tmp_path):
    model = SphereDensity()
    n = 32
    out = tmp_path / "sphere.ply"
    summary = run_mesh(
        WorkDir.at(tmp_path), MeshConfig(resolution=n, out=str(out)), progress=False, model=model
    )
    assert 0.0 < summary["threshold"] < 100.0 and summary["threshold_rule"] != "given"
    v, _ = read_ply(out)
    r = np.linalg.norm(v - model.sphere_centre, axis=1)
    voxel = (2 * model.scale / (n - 1)).max()
    assert abs(r.mean() - model.radius) < 0.5 * voxel and r.std() < 0.3 * voxel


def test_default_level_is_where_rays_reach_half_transmittance_and_stable_in_resolution():
    blob = SoftBlob()
    levels = {}
    for n in (33, 65):
        grid = density_grid(blob, n, progress=False)
        got = surface_level(grid)
        levels[n] = got["level"]
        assert 0 < got["rays"] < got["rays_total"] == 6 * n * n
        assert float(grid.min()) < got["level"] < float(grid.max())
    assert levels[33] == pytest.approx(levels[65], rel=0.03)
    # the central axis ray, entering at x = -1 (normalised): its T = 1/2 point, by a fine 1D integral
    s = np.linspace(-1.0, 0.0, 200001)
    r_world = np.abs(s) * blob.scale[0]
    sigma = blob.amplitude * np.exp(-((r_world / blob.width) ** 2))
    tau = np.concatenate([[0.0], np.cumsum(0.5 * (sigma[1:] + sigma[:-1]) * np.diff(s))])
    central = sigma[np.searchsorted(tau, np.log(2.0))]
    # rays off the centre cross at lower densities (they pass less matter), so the median is below the centre's
    assert 0.2 * central < levels[65] < central


def test_transparent_field_and_bad_extension_are_errors(tmp_path):
    blob = SoftBlob(amplitude=0.1)
    with pytest.raises(LightstageError, match="transparent.*--threshold"):
        run_mesh(
            WorkDir.at(tmp_path),
            MeshConfig(resolution=8, out=str(tmp_path / "m.ply")),
            progress=False,
            model=blob,
        )
    model = SphereDensity()
    for bad in ("mesh.obj", "mesh", "mesh.ply.gz"):
        with pytest.raises(LightstageError, match=r"\.ply"):
            run_mesh(WorkDir.at(tmp_path), MeshConfig(resolution=8, out=str(tmp_path / bad)), progress=False,
                     model=model)  # fmt: skip
    for level in (0.0, -5.0, float("nan")):  # no surface can lie there: refused before the grid is evaluated
        with pytest.raises(LightstageError, match="level > 0"):
            run_mesh(WorkDir.at(tmp_path), MeshConfig(resolution=8, threshold=level, out=str(tmp_path / "m.ply")),
                     progress=False, model=model)  # fmt: skip
    assert model.queries == 0  # refused before any density query
    # an explicit threshold still overrides the rule
    summary = run_mesh(
        WorkDir.at(tmp_path),
        MeshConfig(resolution=16, threshold=50.0, out=str(tmp_path / "M.PLY")),
        progress=False,
        model=model,
    )
    assert summary["threshold"] == 50.0 and summary["threshold_rule"] == "given"


@pytest.fixture(scope="module")
def trained_sphere_work(tmp_path_factory):
    """A work dir with a briefly trained micro checkpoint of the synthetic sphere (about 10 s on one core)."""
    from support.synthetic import SyntheticSphere
    from support.training import micro_config

    from lightstage.training.trainer import fit

    work = WorkDir.at(tmp_path_factory.mktemp("mesh") / "work")
    cfg = micro_config(200, 64, checkpoint_every=200)
    cfg.optim.lr = 2e-2
    sphere = SyntheticSphere(batch_size=64)
    fit(cfg, sphere, work.train_dir, sphere.centre, sphere.scale, progress=False)
    return work, sphere


@pytest.mark.slow
def test_cli_mesh_default_level_on_a_trained_checkpoint(trained_sphere_work, tmp_path, capsys):
    from lightstage.pipelines.cli import main

    work, sphere = trained_sphere_work
    out = tmp_path / "m.ply"
    assert main(["mesh", str(work.root), "--resolution", "24", "--device", "cpu", "--out", str(out)]) == 0
    summary = json.loads(out.with_suffix(".json").read_text())
    lo, hi = summary["density_range"]
    assert lo < summary["threshold"] < hi and summary["vertices"] > 100
    v, _ = read_ply(out)
    c = np.asarray(sphere.centre)
    assert np.all(v >= c - sphere.scale - 1e-4) and np.all(v <= c + sphere.scale + 1e-4)
    assert np.linalg.norm(v.mean(axis=0) - c) < 0.1  # a closed blob around the sphere, not the box's walls
    r = np.linalg.norm(v - c, axis=1)
    assert 0.25 < np.median(r) < 0.7  # true radius 0.5; a 200-step micro model is soft
    capsys.readouterr()
    assert main(["mesh", str(work.root), "--resolution", "8", "--out", str(tmp_path / "m.obj")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("lightstage: error:") and err.count("\n") == 1 and ".ply" in err
