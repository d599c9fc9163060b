"""The basis-light weights (lightstage.training.light_basis), the compressed basis (lightstage.viewer.compress)
and the shared-density OLAT renders (lightstage.training.olat_basis)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from lightstage.cameras import PinholeCamera, look_at
from lightstage.errors import LightstageError
from lightstage.training.envmap import EnvMap, pixel_directions, row_solid_angles
from lightstage.training.light_basis import (
    LightBasis,
    envmap_weights,
    relight_basis,
    rotation_table,
    sphere_directions,
    stage_directions,
    stage_lights,
)
from lightstage.viewer.compress import compress_basis, rank_for


def _cap_directions(n: int = 30, seed: int = 0) -> np.ndarray:
    """Random directions above 10 deg elevation: the centre lies outside their hull (a rim exists)."""
    rng = np.random.default_rng(seed)
    z = rng.uniform(np.sin(np.deg2rad(10)), 1.0, n)
    phi = rng.uniform(0, 2 * np.pi, n)
    r = np.sqrt(1 - z**2)
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], 1)


@pytest.mark.parametrize("dirs", [sphere_directions(40), sphere_directions(25, -90), _cap_directions()])
def test_a_light_at_a_basis_light_gets_exactly_that_light(dirs):
    basis = LightBasis.of(dirs)
    w = basis.weights(dirs)
    assert np.allclose(w, np.eye(len(dirs)), atol=1e-12)


@pytest.mark.parametrize("dirs", [sphere_directions(40), _cap_directions()])
def test_weights_are_a_continuous_partition_of_unity_on_at_most_three_lights(dirs):
    basis = LightBasis.of(dirs)
    rng = np.random.default_rng(1)
    q = rng.normal(size=(3000, 3))
    w = basis.weights(q)
    assert np.all(w >= 0) and np.allclose(w.sum(1), 1.0) and (w > 0).sum(1).max() <= 3
    # inside a facet the weighted corners point exactly along the query (planar barycentric coordinates)
    covered = (w > 0).sum(1) == 3
    p = w[covered] @ basis.directions
    qn = q[covered] / np.linalg.norm(q[covered], axis=1, keepdims=True)
    assert np.allclose(p / np.linalg.norm(p, axis=1, keepdims=True), qn, atol=1e-9)
    # continuity: a tiny move changes the weights a little, also across facet edges and the rim
    step = basis.weights(q + 1e-7 * rng.normal(size=q.shape))
    assert np.abs(step - w).max() < 1e-4


def test_directions_below_the_lights_take_the_nearest_rim_point():
    dirs = _cap_directions()
    basis = LightBasis.of(dirs)
    assert len(basis.rim) > 0
    w = basis.weights(np.array([[0.0, 0.0, -1.0], [1.0, 0.2, -0.3]]))
    assert np.allclose(w.sum(1), 1.0) and (w > 0).sum(1).max() <= 2
    rim_lights = set(basis.rim.ravel().tolist())
    assert set(np.flatnonzero(w.sum(0)).tolist()) <= rim_lights


def test_degenerate_bases_are_refused_or_handled():
    with pytest.raises(LightstageError, match="same direction"):
        LightBasis.of(np.array([[0, 0, 1.0], [0, 0, 2.0], [1, 0, 0]]))
    ring = np.array([[np.cos(a), np.sin(a), 0.0] for a in np.linspace(0, 2 * np.pi, 6, endpoint=False)])
    with pytest.raises(LightstageError, match="one plane through the centre"):
        LightBasis.of(ring)
    two = LightBasis.of(np.array([[1.0, 0, 0], [0, 1.0, 0]]))
    assert np.allclose(two.weights(np.array([[1.0, 1.0, 0.3]])), [[0.5, 0.5]])
    one = LightBasis.of(np.array([[0, 0, 1.0]]))
    assert np.allclose(one.weights(np.array([[1.0, 0, 0]])), [[1.0]])


def test_envmap_weights_of_one_pixel_at_a_basis_light():
    """A map black but for one pixel of radiance L gives that pixel's light L * Omega * d^2 / I, nothing else."""
    h, w = 8, 16
    radiance = np.zeros((h, w, 3))
    radiance[2, 5] = [1.0, 2.0, 3.0]
    env = EnvMap(radiance)
    dirs = np.vstack([pixel_directions(h, w)[2, 5], sphere_directions(20)])
    weights = envmap_weights(env, LightBasis.of(dirs), olat_factor=2.25)
    expected = np.zeros_like(weights)
    expected[0] = radiance[2, 5] * row_solid_angles(h, w)[2] * 2.25
    assert np.allclose(weights, expected, atol=1e-15)


def test_rotation_table_rows_equal_the_turned_maps_weights():
    rng = np.random.default_rng(2)
    env = EnvMap(rng.random((8, 16, 3)), rotate_deg=12.5)
    basis = LightBasis.of(sphere_directions(30))
    table = rotation_table(env, basis, 1.7, steps=36)
    for k in (0, 1, 17, 35):
        turned = dataclasses.replace(env, rotate_deg=12.5 + 10.0 * k)
        assert np.allclose(table[k], envmap_weights(turned, basis, 1.7), rtol=1e-10, atol=1e-14)
    # a full-sphere basis keeps all the map's energy
    assert np.allclose(table.sum(1), env.energies().sum((0, 1)) * 1.7)


def test_stage_directions_spread_over_the_union_of_groups():
    a = sphere_directions(10)
    b = a @ np.array([[0, -1, 0], [1, 0, 0], [0, 0, 1.0]]).T  # the rig turned by 90 deg
    d = stage_directions({"000": a, "090": b, "dup": a}, 12)
    assert d.shape == (12, 3) and np.allclose(np.linalg.norm(d, axis=1), 1)
    assert len(stage_directions({"000": a, "dup": a}, 100)) == 10  # repeats dropped


def test_compression_meets_the_stated_error_bound():
    rng = np.random.default_rng(3)
    L, H, W = 24, 20, 30
    low = np.einsum("lk,khwc->lhwc", rng.random((L, 5)), rng.random((5, H, W, 3)))
    images = (low + 0.02 * rng.random((L, H, W, 3))).astype(np.float32)
    ranks = []
    for tol in (0.05, 0.01, 0.002):
        comp = compress_basis(images, tol, 64, crop=False)
        err = np.linalg.norm(comp.reconstruct() - images) / np.linalg.norm(images)
        assert err <= tol and comp.relative_error == pytest.approx(err, rel=1e-3, abs=1e-6)
        assert comp.components.dtype == np.float16 and np.abs(comp.components).max() <= 1.0
        ranks.append(comp.rank)
    assert ranks[0] < ranks[1] < ranks[2] <= L
    capped = compress_basis(images, 0.0, 3, crop=False)
    assert capped.rank == 3 and capped.relative_error > 0.002
    s = np.linalg.svd(images.reshape(L, -1).astype(np.float64), compute_uv=False)
    assert rank_for(s, 0.05) == ranks[0] or ranks[0] == rank_for(s, 0.05) + 1  # +1 only for half rounding


def test_crop_keeps_every_non_zero_pixel_and_a_basis_light_reproduces_its_image():
    rng = np.random.default_rng(4)
    images = np.zeros((6, 16, 24, 3), np.float32)
    images[:, 3:9, 5:20] = rng.random((6, 6, 15, 3))
    comp = compress_basis(images, 0.0, 16)
    assert comp.crop == (4, 2, 17, 8)
    basis = LightBasis.of(sphere_directions(6))
    for light in range(6):
        weights = basis.point_weights(basis.directions[light])
        img = comp.reconstruct(weights)
        assert np.allclose(img, images[light], atol=2e-3)
        assert np.allclose(relight_basis(images, weights), images[light])


# ---- the shared-density OLAT renders --------------------------------------------------------------------
def _random_model(field: str, min_weight: float, n_coarse: int = 0, light: str = "distant"):
    from lightstage.training.config import load_config
    from lightstage.training.inference import TrainedModel
    from lightstage.training.model import RelightModel

    over = {
        "model": {
            "field": field,
            "n_coarse": n_coarse,
            "n_fine": 12,
            "min_weight": min_weight,
            "light": light,
            "density_bias": 2.0,
            "h_bias_init": 0.0,
            "mlp": {"depth": 2, "width": 16, "skip": 1, "head_width": 8, "pos_freqs": 2},
            "hashgrid": {"levels": 2, "log2_table_size": 8, "max_resolution": 32, "hidden": 16},
        }
    }
    cfg = load_config("cpu" if field == "hashgrid" else "tiny", over)
    torch.manual_seed(0)
    net = RelightModel(cfg.model, [0.0, 0.0, 0.0], 0.5)
    for p in net.parameters():
        p.data.normal_(0.0, 0.5)
    if light == "point":  # lights 1 m from a point off the scene centre: directions and falloff vary
        net.set_light_frame([0.05, 0.0, -0.02], 1.0)
    return TrainedModel(net, cfg)


@pytest.mark.parametrize(
    "field, min_weight, n_coarse, light",
    [("hashgrid", 1e-3, 0, "distant"), ("hashgrid", 0.0, 8, "distant"), ("mlp", 0.0, 8, "distant"),
     ("hashgrid", 1e-3, 0, "point")],
)  # fmt: skip
def test_olat_basis_equals_one_render_per_light(field, min_weight, n_coarse, light):
    from lightstage.training.olat_basis import render_olat_basis

    model = _random_model(field, min_weight, n_coarse, light)
    R, t = look_at(np.array([1.2, 0.4, 0.5]), np.zeros(3))
    K = np.array([[20.0, 0, 8], [0, 20.0, 6], [0, 0, 1]])
    camera = PinholeCamera(K, R, t, 16, 12)
    dirs = sphere_directions(5)
    images = render_olat_basis(model, camera, dirs, chunk=50)
    for light in range(5):
        ref = model.image_from_camera(camera, dirs[light])
        assert np.abs(ref).max() > 0
        assert np.allclose(images[light], ref, rtol=1e-4, atol=1e-6 * np.abs(ref).max())


def test_relight_stage_is_the_basis_relit_with_the_envmap_weights(tmp_path):
    """`lightstage relight --lights stage` gives the image the viewer computes for the same envmap."""
    from lightstage.frames import read_exr, write_exr
    from lightstage.training.light_basis import stage_basis
    from lightstage.training.olat_basis import render_olat_basis
    from lightstage.training.relight import RelightConfig, run_relight
    from lightstage.training.view_specs import load_scene_info, parse_camera
    from lightstage.workdir import WorkDir

    model = _random_model("hashgrid", 1e-3)
    rng = np.random.default_rng(5)
    write_exr(tmp_path / "env.exr", rng.random((8, 16, 3)).astype(np.float32), half=False)
    work = WorkDir.at(tmp_path / "work")
    work.root.mkdir()
    spec = "orbit:size=12x8"
    cfg = RelightConfig(
        envmap=str(tmp_path / "env.exr"), lights="stage", cameras=[spec], resolution="16x8", rotate_deg=30,
        out=str(tmp_path / "out"),
    )  # fmt: skip
    summary = run_relight(work, cfg, progress=False, model=model)
    img = read_exr(tmp_path / "out" / "orbit_az0_el20_stage.exr")[..., :3]
    scene = load_scene_info(work)
    basis = stage_basis(None)
    camera = parse_camera(spec, scene, model).camera
    from lightstage.training.envmap import load_envmap

    env = load_envmap(tmp_path / "env.exr", (16, 8), 30)
    expected = relight_basis(
        render_olat_basis(model, camera, basis.directions), envmap_weights(env, basis, 2.25)
    )
    assert summary["views"]["orbit_az0_el20"]["results"]["stage"]["lights"] == len(basis)
    assert np.allclose(img, expected, rtol=2e-3, atol=1e-3 * np.abs(expected).max())
    assert np.allclose(stage_lights(env, basis).rgb * 2.25, envmap_weights(env, basis, 2.25))


def test_the_hash_grid_uses_the_factored_transfer():
    """The per-light stage really is the cheap one (a layout change would fall back, silently slower)."""
    from lightstage.training.olat_basis import FactoredTransfer

    net = _random_model("hashgrid", 1e-3).model
    x = torch.rand(40, 3) * 2 - 1
    view = torch.nn.functional.normalize(torch.randn(40, 3), dim=-1)
    feat = net.fine.geometry(x)[1].detach()
    fast = FactoredTransfer.of(net.fine, feat, view)
    assert isinstance(fast, FactoredTransfer)
    light = torch.nn.functional.normalize(torch.tensor([0.1, 0.7, 0.2]), dim=0)
    with torch.no_grad():
        assert torch.allclose(fast(light), net.fine.transfer(feat, view, light.expand(40, 3)), rtol=1e-5)
