"""Volume rendering math against closed forms; ray-box intersection; hierarchical resampling."""

from __future__ import annotations

import math

import torch

from lightstage.training.render import composite, composite_rows, volume_weights
from lightstage.training.sampling import merge_edges, midpoints, ray_box, resample_edges, stratified_edges


def test_single_slab_weights_match_closed_form():
    # density s0 on [a, b], zero elsewhere; edges aligned with the slab boundaries
    s0, a, b = 3.0, 0.5, 1.25
    edges = torch.linspace(0.0, 2.0, 33)[None]
    t, delta = midpoints(edges)
    sigma = torch.where((t > a) & (t < b), torch.tensor(s0), torch.tensor(0.0))
    w = volume_weights(sigma, delta)[0]
    # total opacity = 1 - exp(-s0 (b - a)); each inside sample: exp(-s0 (t0 - a)) (1 - exp(-s0 delta))
    assert math.isclose(float(w.sum()), 1 - math.exp(-s0 * (b - a)), rel_tol=1e-5)
    inside = (t[0] > a) & (t[0] < b)
    t0 = edges[0, :-1]
    expected = torch.exp(-s0 * (t0 - a)) * (1 - torch.exp(-s0 * delta[0]))
    torch.testing.assert_close(w[inside], expected[inside], rtol=1e-5, atol=1e-7)
    assert float(w[~inside].abs().max()) == 0.0
    # a constant transfer gradient h composites to h * opacity
    h = torch.full((1, 32, 3), 0.7)
    torch.testing.assert_close(
        composite(w[None], h)[0], torch.full((3,), 0.7 * (1 - math.exp(-s0 * (b - a))))
    )


def test_opacity_independent_of_sampling_density():
    for n in (4, 64, 1000):
        edges = torch.linspace(0.0, 1.0, n + 1)[None]
        _, delta = midpoints(edges)
        w = volume_weights(torch.full((1, n), 2.0), delta)
        assert math.isclose(float(w.sum()), 1 - math.exp(-2.0), rel_tol=1e-5)


def test_ray_box_hits_and_misses():
    o = torch.tensor([[-3.0, 0.0, 0.0], [-3.0, 5.0, 0.0], [0.0, 0.0, 0.0]])
    d = torch.tensor([[1.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    near, far = ray_box(o, d)
    torch.testing.assert_close(near, torch.tensor([2.0, near[1].item(), 0.0]))
    torch.testing.assert_close(far[[0, 2]], torch.tensor([4.0, 1.0]))
    assert far[1] == near[1]  # miss: zero-length interval -> zero weights


def test_stratified_edges_span_near_far_and_resampling_concentrates():
    near, far = torch.tensor([1.0, 2.0]), torch.tensor([3.0, 2.0])
    torch.manual_seed(0)
    e = stratified_edges(near, far, 16, randomized=True)
    assert torch.all(e[:, 1:] >= e[:, :-1])
    torch.testing.assert_close(e[:, 0], near)
    torch.testing.assert_close(e[:, -1], far)
    w = torch.zeros(2, 16)
    w[0, 5] = 1.0  # all mass in one interval
    r = resample_edges(e, w, 64, randomized=False, padding=0.0)
    inside = (r[0] >= e[0, 5] - 1e-6) & (r[0] <= e[0, 6] + 1e-6)
    assert inside.float().mean() > 0.9
    torch.testing.assert_close(r[1], torch.full((65,), 2.0))  # missed ray stays degenerate
    m = merge_edges(e, r)
    assert m.shape == (2, 17 + 65) and torch.all(m[:, 1:] >= m[:, :-1])


def test_composite_rows_equals_composite_of_the_scattered_samples():
    """Compositing only the kept samples into their rays equals `composite` over the full (R, S) layout with
    the dropped samples at 0, values and gradients alike (the CPU training path uses the packed form)."""
    g = torch.Generator().manual_seed(3)
    keep = torch.rand(5, 7, generator=g) > 0.4
    keep[2] = False  # a ray with no kept sample composites to 0
    w_full = torch.rand(5, 7, generator=g, dtype=torch.float64).requires_grad_()
    vals = torch.randn(int(keep.sum()), 3, generator=g, dtype=torch.float64).requires_grad_()
    rows = keep.nonzero(as_tuple=True)[0]
    packed = composite_rows(w_full[keep], vals, rows, 5)
    dense = torch.zeros(5, 7, 3, dtype=torch.float64).masked_scatter(keep[..., None], vals)
    full = composite(w_full, dense)
    torch.testing.assert_close(packed, full)
    assert torch.all(packed[2] == 0)
    up = torch.randn(5, 3, generator=g, dtype=torch.float64)
    gw_p, gv_p = torch.autograd.grad(packed, (w_full, vals), up)
    gw_f, gv_f = torch.autograd.grad(full, (w_full, vals), up)
    torch.testing.assert_close(gw_p[keep], gw_f[keep])
    torch.testing.assert_close(gv_p, gv_f)
    assert torch.all(gw_p[~keep] == 0)
