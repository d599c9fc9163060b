"""The CPU-fast pieces of the hash-grid field: the vectorised encoding equals the per-level reference lookup
(forward and gradient), the transfer stage skipped below min_weight changes pixels by less than that weight,
samples stay inside the scene box, and the occupancy grid starts from the visual hull."""

from __future__ import annotations

import pytest
import torch
from support.training import rays_into_origin

from lightstage.training import hashgrid_cpu
from lightstage.training.config import load_config
from lightstage.training.encoding import positional_encoding
from lightstage.training.hashgrid import CORNERS, PRIMES, HashGridEncoding
from lightstage.training.model import RelightModel
from lightstage.training.occupancy import hull_prior


def _reference(enc: HashGridEncoding, x: torch.Tensor) -> torch.Tensor:
    """Level by level, 64-bit spatial hash (x*1 ^ y*2654435761 ^ z*805459861) mod T, as Mueller et al."""
    u = ((x + 1.0) * 0.5).clamp(0.0, 1.0)
    out = []
    for level, res in enumerate(enc.resolutions.tolist()):
        pos = u * res
        cell = torch.floor(pos).long().clamp(max=res - 1)
        frac = pos - cell
        v = cell[:, None, :] + CORNERS
        if enc.dense[level]:
            idx = v[..., 0] + (res + 1) * (v[..., 1] + (res + 1) * v[..., 2])
        else:
            idx = (
                (v[..., 0] * PRIMES[0]) ^ (v[..., 1] * PRIMES[1]) ^ (v[..., 2] * PRIMES[2])
            ) % enc.table_size
        w = torch.where(CORNERS.bool(), frac[:, None, :], 1.0 - frac[:, None, :]).prod(-1)
        out.append((enc.level_table(level)[idx] * w[..., None]).sum(1))
    return torch.cat(out, dim=-1)


@pytest.mark.parametrize("kernel", ["numba", "torch"])
@pytest.mark.parametrize(
    "levels,features,log2_t,max_res",
    [(16, 2, 19, 2048), (8, 2, 17, 512), (4, 2, 10, 64), (3, 1, 10, 64), (3, 4, 8, 32)],
)
def test_vectorised_encoding_equals_reference(levels, features, log2_t, max_res, kernel):
    """Both CPU paths: the fused numba kernels (the default) and the PyTorch one (CUDA's, and the fallback)."""
    old = hashgrid_cpu.set_enabled(kernel == "numba")
    try:
        _check_against_reference(HashGridEncoding(levels, features, log2_t, 16, max_res))
    finally:
        hashgrid_cpu.set_enabled(old)


def _check_against_reference(enc: HashGridEncoding) -> None:
    torch.manual_seed(0)
    with torch.no_grad():
        enc.tables.normal_()
    x = torch.rand(2000, 3) * 2 - 1
    x[:5], x[5:10] = 1.0, -1.0  # the cube's faces
    got, want = enc(x), _reference(enc, x)
    torch.testing.assert_close(got, want, atol=1e-5, rtol=1e-5)
    g = torch.randn_like(got)
    (got * g).sum().backward()
    grad = enc.tables.grad.clone()
    enc.tables.grad = None
    (_reference(enc, x) * g).sum().backward()
    torch.testing.assert_close(grad, enc.tables.grad, atol=1e-5, rtol=1e-5)


def _rays(n: int = 256):
    return rays_into_origin(n, seed=1, spread=0.15)


def test_transfer_skipped_only_below_min_weight():
    cfg = load_config("cpu").model
    model = RelightModel(cfg, [0.0, 0.0, 0.0], 1.0)
    with torch.no_grad():  # a dense blob so weights vary along rays
        model.fine.geo[-1].bias[0] = 5.0  # opaque enough that the last samples weigh < min_weight
    o, d, light = _rays()
    full = RelightModel(load_config("cpu", {"model": {"min_weight": 0.0}}).model, [0.0, 0.0, 0.0], 1.0)
    full.load_state_dict(model.state_dict())
    with torch.no_grad():  # rendering: the transfer stage is skipped below min_weight
        a, b = model(o, d, light)["rgb"], full(o, d, light)["rgb"]
    torch.testing.assert_close(model(o, d, light)["rgb"], b)  # training evaluates every kept sample
    h_max = 1.0  # exp(h) at init is ~exp(-3); bound the skipped mass by min_weight * samples * max h
    assert (a - b).abs().max() <= cfg.min_weight * cfg.n_fine * h_max
    assert (a - b).abs().max() > 0 or cfg.min_weight == 0


def test_samples_stay_inside_the_box_and_density_outside_is_zero():
    cfg = load_config("cpu").model
    box = [[-0.2, -0.1, -0.5], [0.2, 0.1, 0.3]]
    model = RelightModel(cfg, [0.0, 0.0, 0.0], 1.0, box=box)
    o, d, _ = _rays(64)
    seen = []
    # every evaluated position passes the hash encoding (module MLPs or the chunked fused ones alike)
    model.fine.encoding.register_forward_pre_hook(lambda m, args: seen.append(args[0].detach().clone()))
    model(o, d, torch.nn.functional.normalize(torch.ones(64, 3), dim=-1))
    x = torch.cat(seen)
    lo, hi = torch.tensor(box[0]), torch.tensor(box[1])
    assert ((x >= lo - 1e-6) & (x <= hi + 1e-6)).all()
    outside = torch.tensor([[0.5, 0.0, 0.0], [0.0, 0.0, 0.8]])
    assert (model.density(outside) == 0).all()


def test_hull_prior_marks_exactly_the_overlapping_cells():
    hull = torch.zeros(10, 10, 10, dtype=torch.bool)
    hull[4:6, 4:6, 4:6] = True  # voxels 4, 5 of 10 over [-0.5, 0.5]: [-0.1, 0.1]; dilated [-0.2, 0.2]
    prior = hull_prior(hull, torch.tensor([-0.5] * 3), torch.tensor([0.5] * 3), 16)
    idx = prior.nonzero()
    # cells of 0.125 overlapping [-0.2, 0.2]: [-0.25, 0.25] = cells 6..9
    assert prior.sum() == 4**3 and idx.min() == 6 and idx.max() == 9
    cfg = load_config("cpu").model
    model = RelightModel(cfg, [0.0, 0.0, 0.0], 1.0, box=[[-0.5] * 3, [0.5] * 3], hull=hull)
    occ = model.occupancy
    # a 0.4-wide cube (+ one 1/32 cell each side at most) of the 2-wide unit cube, from step 0
    assert bool(occ.ready) and (0.4 / 2) ** 3 <= occ.occupied_fraction() <= ((0.4 + 2 / 32) / 2) ** 3
    assert occ.occupied(torch.tensor([[0.0, 0.0, 0.0]])).all()
    assert not occ.occupied(torch.tensor([[0.4, 0.4, 0.4]])).any()


def test_half_vector_input_widens_the_head_and_trains():
    from lightstage.training.encoding import encoded_dim

    cfg = load_config("cpu").model
    assert cfg.hashgrid.half_freqs == 4
    model = RelightModel(cfg, [0.0, 0.0, 0.0], 1.0)
    g = cfg.hashgrid
    want = g.geo_features + encoded_dim(g.dir_freqs) + encoded_dim(g.light_freqs) + encoded_dim(g.half_freqs)
    assert model.fine.head[0].in_features == want
    o, d, light = _rays(32)
    model(o, d, light)["rgb"].sum().backward()
    assert model.fine.head[0].weight.grad.abs().sum() > 0


@pytest.mark.parametrize("per_ray_light", [True, False])
def test_per_ray_transfer_equals_per_sample(per_ray_light):
    """The head's first layer applied to per-ray inputs once per ray and gathered equals the per-sample
    computation (view per ray; light per ray or per sample)."""
    torch.manual_seed(0)
    model = RelightModel(load_config("cpu").model, [0.0, 0.0, 0.0], 1.0)
    field = model.fine
    rows = torch.randint(0, 16, (200,))
    feat = torch.randn(200, field.cfg.hashgrid.geo_features)
    view = torch.nn.functional.normalize(torch.randn(16, 3), dim=-1)
    light = torch.nn.functional.normalize(torch.randn(16 if per_ray_light else 200, 3), dim=-1)
    got = field.transfer(feat, view, light, rows=rows, per_ray_light=per_ray_light)
    g = field.cfg.hashgrid
    v, lt = view[rows], light[rows] if per_ray_light else light
    half = torch.nn.functional.normalize(lt - v, dim=-1)
    pe = positional_encoding
    inputs = torch.cat([feat, pe(v, g.dir_freqs), pe(lt, g.light_freqs), pe(half, g.half_freqs)], -1)
    want = torch.exp(field.head(inputs))  # the head as one MLP on the concatenated inputs
    torch.testing.assert_close(got, want, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(field.transfer(feat, v, lt), want, rtol=1e-5, atol=1e-6)


def test_occupancy_updates_only_its_region():
    """An update evaluates the density only in the region's cells (the hull prior, else the cells overlapping
    the box); cells outside stay empty even where the untrained field is dense."""
    from lightstage.training.occupancy import OccupancyGrid, box_cells

    region = box_cells(torch.tensor([-0.5, -1.0, -1.0]), torch.tensor([-0.2, 1.0, 1.0]), 8)
    # cells of 0.25 meeting x in [-0.5, -0.2] (closed: a cell that only touches counts): x cells 1, 2, 3
    assert region.sum() == 3 * 8 * 8 and region[1:4].all()
    occ = OccupancyGrid(8, 0.95, 1.0, region)
    seen = []
    occ.update(lambda x: (seen.append(x), torch.full((len(x),), 100.0))[1], seed=0)
    pts = torch.cat(seen)
    assert len(pts) == int(region.sum()) and (pts[:, 0] >= -0.75).all() and (pts[:, 0] <= 0.0).all()
    assert (occ.grid > occ.density_threshold).eq(region).all()
    cfg = load_config("cpu").model
    hull = torch.zeros(10, 10, 10, dtype=torch.bool)
    hull[4:6, 4:6, 4:6] = True
    model = RelightModel(cfg, [0.0, 0.0, 0.0], 1.0, box=[[-0.5] * 3, [0.5] * 3], hull=hull)
    model.occupancy.update(lambda x: torch.full((len(x),), 1e6), seed=1)
    assert model.occupancy.occupied_fraction() == float(model.occupancy.region.float().mean())
    assert not model.occupancy.occupied(torch.tensor([[0.4, 0.4, 0.4]])).any()


def test_hull_prior_equals_a_point_by_point_reference():
    """The separable gather marks the same cells as testing every probe point against the dilated hull."""
    gen = torch.Generator().manual_seed(0)
    hull = torch.rand(7, 5, 9, generator=gen) > 0.8
    lo, hi = torch.tensor([-0.6, -0.3, -0.9]), torch.tensor([0.5, 0.4, 0.7])
    res, samples = 10, 3
    dil = torch.nn.functional.max_pool3d(hull.float()[None, None], 3, stride=1, padding=1)[0, 0] > 0
    n = torch.tensor(hull.shape, dtype=torch.float32)
    want = torch.zeros((res,) * 3, dtype=torch.bool)
    sub = (torch.arange(samples) + 0.5) / samples
    for c in torch.cartesian_prod(*(torch.arange(res),) * 3):
        for s in torch.cartesian_prod(sub, sub, sub):
            rel = ((c + s) / res * 2 - 1 - lo) / (hi - lo) * n
            if ((rel >= 0) & (rel < n)).all() and dil[tuple(rel.long().tolist())]:
                want[tuple(c.tolist())] = True
                break
    assert torch.equal(hull_prior(hull, lo, hi, res, samples), want)
