"""The chunked field MLPs (`training/fused_mlp.py`) equal the module path: the function against `nn.Linear`/ReLU
layers (outputs and every gradient, chunk boundaries included, float64 gradcheck), and the whole model's pixels
and parameter gradients with the fused path on and off for the CPU configs that use it."""

from __future__ import annotations

import pytest
import torch
from support.training import rays_into_origin
from torch import nn

from lightstage.training import fused_mlp, hashgrid
from lightstage.training.config import load_config
from lightstage.training.model import RelightModel


def _layers(sizes: list[int], dtype=torch.float32) -> list[nn.Linear]:
    return [nn.Linear(a, b, dtype=dtype) for a, b in zip(sizes[:-1], sizes[1:], strict=True)]


def _reference(enc, ray_term, rows, geo: list[nn.Linear], head: list[nn.Linear]):
    """The two MLPs as modules: geo with ReLU between layers; head on geo[:, 1:] plus the per-ray term."""
    x = enc
    for i, layer in enumerate(geo):
        x = layer(x)
        if i < len(geo) - 1:
            x = torch.relu(x)
    g = x
    x = head[0](g[:, 1:]) + ray_term[rows]
    for layer in head[1:]:
        x = layer(torch.relu(x))
    return g, x


@pytest.mark.parametrize("n,chunk", [(50, 7), (64, 64), (1000, 256), (3, 8192)])
def test_outputs_and_gradients_equal_the_module_path(n, chunk):
    torch.manual_seed(0)
    geo, head = _layers([12, 32, 16]), _layers([15, 24, 24, 3])
    enc = torch.randn(n, 12, requires_grad=True)
    ray_term = torch.randn(9, 24, requires_grad=True)
    rows = torch.randint(0, 9, (n,))
    params = [p for m in (*geo, *head) for p in m.parameters()]
    g_want, h_want = _reference(enc, ray_term, rows, geo, head)
    dg, dh = torch.randn_like(g_want), torch.randn_like(h_want)
    want = torch.autograd.grad((g_want * dg).sum() + (h_want * dh).sum(), [enc, ray_term, *params])
    g_got, h_got = fused_mlp.field_mlp(
        enc,
        ray_term,
        rows,
        [(m.weight, m.bias) for m in geo],
        [(m.weight, m.bias) for m in head],
        chunk=chunk,
    )
    torch.testing.assert_close(g_got, g_want, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(h_got, h_want, rtol=1e-5, atol=1e-6)
    got = torch.autograd.grad((g_got * dg).sum() + (h_got * dh).sum(), [enc, ray_term, *params])
    for a, b in zip(got, want, strict=True):
        torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-5)


def test_gradcheck_in_float64_across_chunks():
    torch.manual_seed(1)
    geo, head = _layers([5, 6, 4], torch.float64), _layers([3, 6, 2], torch.float64)
    enc = torch.randn(11, 5, dtype=torch.float64, requires_grad=True)
    ray_term = torch.randn(4, 6, dtype=torch.float64, requires_grad=True)
    rows = torch.randint(0, 4, (11,))
    params = [p for m in (*geo, *head) for p in m.parameters()]

    def fn(e, r, *ps):
        pairs = list(zip(ps[0::2], ps[1::2], strict=True))
        return fused_mlp.field_mlp(e, r, rows, pairs[:2], pairs[2:], chunk=4)

    assert torch.autograd.gradcheck(fn, (enc, ray_term, *params))


def test_only_the_head_output_used():
    """The density output unused (its gradient zero) still gives the head's and the trunk's gradients."""
    torch.manual_seed(2)
    geo, head = _layers([8, 16, 8]), _layers([7, 16, 3])
    enc, ray_term, rows = torch.randn(40, 8), torch.randn(5, 16), torch.randint(0, 5, (40,))
    _, h = fused_mlp.field_mlp(
        enc, ray_term, rows, [(m.weight, m.bias) for m in geo], [(m.weight, m.bias) for m in head], 16
    )
    h.sum().backward()
    _, h_ref = _reference(enc, ray_term, rows, geo, head)
    got = [p.grad.clone() for m in (*geo, *head) for p in m.parameters()]
    for m in (*geo, *head):
        m.zero_grad()
    h_ref.sum().backward()
    want = [p.grad for m in (*geo, *head) for p in m.parameters()]
    for a, b in zip(got, want, strict=True):
        torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-5)


@pytest.mark.parametrize("config", ["fast", "cpu"])
def test_model_pixels_and_gradients_equal_with_fused_on_and_off(config, monkeypatch):
    cfg = load_config(config).model
    if cfg.light == "point":
        pytest.skip(f"{config} uses point lights; the fused path runs for distant lights only")
    torch.manual_seed(4)
    model = RelightModel(cfg, [0.0, 0.0, 0.0], 1.0)
    with torch.no_grad():  # away from init so every layer's gradient is non-trivial
        for p in model.parameters():
            p.add_(torch.randn_like(p) * 0.05)
    o, d, light = rays_into_origin(128, seed=3, spread=0.2)
    results = {}
    calls = []
    real = fused_mlp._FieldMLP.apply
    monkeypatch.setattr(fused_mlp._FieldMLP, "apply", lambda *a: (calls.append(1), real(*a))[1])
    for fused in (False, True):
        monkeypatch.setattr(hashgrid, "_FUSED_MLP", fused)
        model.zero_grad()
        calls.clear()
        out = model(o, d, light)
        (out["rgb"] * torch.linspace(0.5, 1.5, 3)).sum().backward()
        assert bool(calls) == fused  # the switch really changes the path
        results[fused] = (out["rgb"].detach(), {k: p.grad.clone() for k, p in model.named_parameters()})
    torch.testing.assert_close(results[True][0], results[False][0], rtol=1e-5, atol=1e-6)
    for k, grad in results[False][1].items():
        torch.testing.assert_close(results[True][1][k], grad, rtol=1e-4, atol=1e-6, msg=k)
    assert any(g.abs().sum() > 0 for g in results[True][1].values())
