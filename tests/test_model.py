"""Model heads and interfaces: exp head finite and non-negative at extreme inputs, config parsing, both fields."""

from __future__ import annotations

import pytest
import torch
from support.synthetic import SyntheticSphere

from lightstage.errors import LightstageError
from lightstage.training.config import TrainConfig, load_config
from lightstage.training.hashgrid import HashGridEncoding
from lightstage.training.heads import density_activation, exp_head
from lightstage.training.model import RelightModel


def test_exp_head_nonnegative_and_finite_at_extremes():
    raw = torch.tensor([-1e30, -1e4, -50.0, 0.0, 50.0, 88.0, 1e4, 1e30, float("inf")])
    h = exp_head(raw, 15.0)
    assert torch.all(torch.isfinite(h)) and torch.all(h >= 0)
    assert float(h.max()) == pytest.approx(torch.exp(torch.tensor(15.0)).item())
    for half in (torch.float16, torch.bfloat16):
        assert torch.all(torch.isfinite(exp_head(raw.to(half), 15.0)))
    s = density_activation(torch.tensor([-1e30, 0.0, 1e30]), "softplus", -1.0)
    assert torch.all(s >= 0) and s[0] == 0


def test_initial_predictions_small_and_missing_rays_black():
    cfg = load_config("tiny")
    model = RelightModel(cfg.model, centre=[0.0, 0.0, 0.0], scale=1.0)
    o = torch.tensor([[0.0, 0.0, -5.0], [5.0, 5.0, -5.0]])
    d = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]])  # second ray misses the unit cube
    out = model(o, d, torch.tensor([[0.0, 0.0, 1.0]] * 2))
    assert torch.all(out["rgb"][0] < 0.2) and torch.all(out["rgb"][1] == 0) and out["acc"][1] == 0


@pytest.mark.parametrize("name", ["tiny", "fast"])
def test_forward_backward_both_fields(name):
    cfg = load_config(name)
    cfg.model.n_fine = 16
    if cfg.model.field == "hashgrid":
        cfg.model.hashgrid.log2_table_size = 12
        cfg.model.hashgrid.max_resolution = 64
        cfg.model.occupancy.resolution = 8
    src = SyntheticSphere(batch_size=64)
    model = RelightModel(cfg.model, src.centre, src.scale)
    b = src.batch(0)
    out = model(b["origins"], b["directions"], b["light_directions"], randomized=True)
    out["rgb"].sum().backward()
    assert out["rgb"].shape == (64, 3) and torch.all(torch.isfinite(out["rgb"]))
    if model.occupancy is not None:
        model.update_occupancy(cfg.model.occupancy.warmup_steps, seed=0)
        assert bool(model.occupancy.ready)


def test_hash_encoding_interpolates_continuously():
    enc = HashGridEncoding(levels=4, features=2, log2_table_size=10, base_resolution=4, max_resolution=32)
    x = torch.rand(100, 3) * 2 - 1
    with torch.no_grad():
        y1, y2 = enc(x), enc(x + 1e-5)
    assert y1.shape == (100, 8) and float((y1 - y2).abs().max()) < 1e-5


def test_config_rejects_unknown_keys_and_bad_types():
    with pytest.raises(LightstageError, match="model.mlp.widht"):
        TrainConfig.from_dict({"model": {"mlp": {"widht": 3}}})
    with pytest.raises(LightstageError, match="optim.lr"):
        TrainConfig.from_dict({"optim": {"lr": "fast"}})
    with pytest.raises(LightstageError, match="model.field"):
        TrainConfig.from_dict({"model": {"field": "voxels"}})
    paper = load_config("paper")
    assert (paper.model.mlp.depth, paper.model.mlp.width, paper.model.mlp.skip) == (8, 256, 4)
    assert (paper.model.n_coarse, paper.model.n_fine, paper.optim.batch_rays) == (64, 128, 4096)
    assert TrainConfig.from_dict(paper.to_dict()) == paper


def _linear(n_in: int, n_out: int) -> int:
    return n_in * n_out + n_out


def test_paper_config_is_the_papers_architecture():
    """Sec. 3.4: per level (coarse, fine) an 8 x 256 density MLP and a separate 8 x 256 transfer-gradient MLP,
    each with the skip (input re-injected) at the fourth layer; exp-activated 3-channel h."""
    from lightstage.training.encoding import encoded_dim

    cfg = load_config("paper")
    m = cfg.model.mlp
    assert (m.h_mlp, m.depth, m.width, m.skip, m.h_depth, m.h_width, m.h_skip) == (
        "separate",
        8,
        256,
        4,
        8,
        256,
        4,
    )
    pos = 3 * (1 + 2 * 10)  # PE(x) with 10 frequencies plus the identity: 63
    dirs = 2 * 3 * (1 + 2 * 4)  # PE(view, 4) and PE(light, 4): 27 each
    assert encoded_dim(m.pos_freqs) == pos and encoded_dim(m.dir_freqs) + encoded_dim(m.light_freqs) == dirs

    def mlp(n_in: int) -> tuple[list[tuple[int, int]], int]:
        shapes = [(256, n_in)] + [(256, 256 + (n_in if i == 4 else 0)) for i in range(1, 8)]
        return shapes, sum(_linear(i, o) for o, i in shapes)

    density_shapes, density_params = mlp(pos)
    h_shapes, h_params = mlp(pos + dirs)
    per_level = density_params + _linear(256, 1) + h_params + _linear(256, 3)
    assert per_level == 1_014_788  # the hand count: 493,313 density + 521,475 transfer gradient

    model = RelightModel(cfg.model, centre=[0.0, 0.0, 0.0], scale=1.0)
    for field in (model.coarse, model.fine):
        assert [tuple(layer.weight.shape) for layer in field.trunk] == density_shapes
        assert tuple(field.sigma.weight.shape) == (1, 256)
        assert [tuple(layer.weight.shape) for layer in field.h_mlp] == h_shapes
        assert tuple(field.h_out.weight.shape) == (3, 256)
        assert sum(p.numel() for p in field.parameters()) == per_level
        assert torch.all(field.h_out.bias == cfg.model.h_bias_init)
    assert sum(p.numel() for p in model.parameters()) == 2 * per_level
    # the transfer MLP does not read the density MLP: h is unchanged when only the density MLP changes
    x = torch.rand(5, 3) * 2 - 1
    v = torch.nn.functional.normalize(torch.randn(5, 3), dim=-1)
    with torch.no_grad():
        s0, h0 = model.fine(x, v, v)
        for p in model.fine.trunk.parameters():
            p.add_(0.1)
        s1, h1 = model.fine(x, v, v)
    assert torch.equal(h0, h1) and not torch.equal(s0, s1)
    assert torch.all(h0 > 0) and h0.shape == (5, 3)


def test_paper_lite_keeps_the_shared_trunk_head():
    cfg = load_config("paper-lite")
    assert cfg.model.mlp.h_mlp == "head" and (cfg.model.mlp.depth, cfg.model.mlp.width) == (8, 256)
    field = RelightModel(cfg.model, centre=[0.0, 0.0, 0.0], scale=1.0).fine
    assert not hasattr(field, "h_mlp") and hasattr(field, "head")
    with pytest.raises(LightstageError, match="h_mlp"):
        TrainConfig.from_dict({"model": {"mlp": {"h_mlp": "shared"}}})
