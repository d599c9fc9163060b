"""The weighted L2 equals its formula, stops the gradient through its denominator, is one-sided on saturated
targets; the mask loss penalises the densities of background rays only, band rays (outside the mask) included."""

from __future__ import annotations

import pytest
import torch

from lightstage.config import ConfigError
from lightstage.training.config import LossConfig
from lightstage.training.losses import mask_loss, measured_epsilon, total_loss, weighted_l2


def test_weighted_l2_formula_and_stop_gradient():
    pred = torch.tensor([[0.5, 0.1, 2.0], [0.01, 0.3, 0.0]], requires_grad=True)
    target = torch.tensor([[0.4, 0.2, 1.0], [0.0, 0.3, 0.5]])
    eps = 1e-3
    loss = weighted_l2(pred, target, eps)
    p = pred.detach()
    expected = (((p - target) / (p + eps)) ** 2).mean()
    torch.testing.assert_close(loss, expected)
    loss.backward()
    # with sg on the denominator: d/dp = 2 (p - y) / (p + eps)^2 / n  (no term from the denominator)
    grad = 2 * (p - target) / (p + eps) ** 2 / p.numel()
    torch.testing.assert_close(pred.grad, grad)
    # without the stop-gradient the gradient would differ
    q = p.clone().requires_grad_(True)
    (((q - target) / (q + eps)) ** 2).mean().backward()
    assert not torch.allclose(q.grad, grad)


def test_saturated_targets_are_one_sided():
    target = torch.tensor([[4.4, 4.4, 4.4], [4.4, 4.4, 4.4]])
    pred = torch.tensor([[5.0, 4.4, 3.0], [5.0, 4.4, 3.0]], requires_grad=True)
    sat = torch.tensor([True, False])
    loss = weighted_l2(pred, target, 1e-3, sat)
    r = (pred.detach() - target) / (pred.detach() + 1e-3)
    r[0, :2] = 0.0  # saturated row: at/above the cutoff costs nothing, below still does
    torch.testing.assert_close(loss, (r**2).mean())
    loss.backward()
    assert pred.grad[0, 0] == 0 and pred.grad[0, 2] != 0 and pred.grad[1, 0] != 0


def test_mask_loss_and_total():
    sigma = torch.tensor([[1.0, 2.0], [3.0, 4.0], [5.0, 6.0]], requires_grad=True)
    bg = torch.tensor([False, True, True])
    torch.testing.assert_close(mask_loss(sigma, bg), torch.tensor((9 + 16 + 25 + 36) / 4.0))
    assert float(mask_loss(sigma, torch.zeros(3, dtype=torch.bool)).detach()) == 0.0
    cfg = LossConfig(rgb_fine=1.0, rgb_coarse=0.5, epsilon=1e-3, mask=0.1)
    rgb = torch.full((3, 3), 0.2)
    outputs = {"rgb": rgb, "rgb_coarse": rgb * 2, "sigma": sigma, "sigma_coarse": sigma * 0}
    batch = {
        "rgb": torch.full((3, 3), 0.1),
        "zone": torch.tensor([2, 0, 0]),
        "saturated": torch.zeros(3, dtype=torch.bool),
    }
    total, parts = total_loss(outputs, batch, cfg)
    expect = (
        weighted_l2(rgb, batch["rgb"], 1e-3)
        + 0.5 * weighted_l2(rgb * 2, batch["rgb"], 1e-3)
        + 0.1 * (86 / 4) / 2
    )
    torch.testing.assert_close(total, expect)
    assert set(parts) == {"rgb_fine", "rgb_coarse", "mask"}


def test_density_loss_covers_band_background_rays():
    """The paper's L2 is on every ray whose target pixel is background: the near-silhouette band's rays are
    outside the mask (dataset/shard_rays.py sampling_zones), so they count; foreground rays do not."""
    from lightstage.dataset.shard_rays import sampling_zones
    from lightstage.workdir import ZONE_BACKGROUND, ZONE_BAND, ZONE_FOREGROUND

    mask = torch.zeros(32, 32, dtype=torch.bool)
    mask[12:20, 12:20] = True
    zones = torch.from_numpy(sampling_zones(mask.numpy(), band_fraction=4 / 32))
    assert not bool(mask[zones == ZONE_BAND].any())  # band pixels are background pixels
    sigma = torch.tensor([[1.0, 1.0], [2.0, 2.0], [3.0, 3.0]])  # fg, band, background rays
    outputs = {"rgb": torch.zeros(3, 3), "sigma": sigma}
    zone = torch.tensor([ZONE_FOREGROUND, ZONE_BAND, ZONE_BACKGROUND])
    batch = {"rgb": torch.zeros(3, 3), "zone": zone, "saturated": torch.zeros(3, dtype=torch.bool)}
    cfg = LossConfig(rgb_fine=1.0, rgb_coarse=0.0, mask=1.0)
    _, parts = total_loss(outputs, batch, cfg)
    assert parts["mask"] == pytest.approx((4 + 4 + 9 + 9) / 4)  # band and background, not foreground
    batch["zone"] = torch.tensor([ZONE_FOREGROUND, ZONE_BAND, ZONE_FOREGROUND])
    assert total_loss(outputs, batch, cfg)[1]["mask"] == pytest.approx(4.0)  # a band ray alone is penalised


def test_epsilon_measured_from_the_data_level():
    fixed = LossConfig(epsilon=1e-3)
    assert measured_epsilon(fixed, exposure=2.5) is fixed  # no epsilon_of_level: the fixed epsilon stays
    rel = LossConfig(epsilon=1e-3, epsilon_of_level=0.03)
    # the level is what the exposure maps to 1: a capture 10x brighter gets a 10x larger epsilon
    assert measured_epsilon(rel, exposure=2.5).epsilon == pytest.approx(0.03 / 2.5)
    assert measured_epsilon(rel, exposure=0.25).epsilon == pytest.approx(0.03 / 0.25)
    with pytest.raises(ConfigError):
        LossConfig(epsilon_of_level=0.0)


def test_our_configs_measure_epsilon_and_the_paper_keeps_rawnerfs():
    """`cpu` and `fast` scale eps with the capture's level (docs/benchmarks.md); `paper` keeps the cited 1e-3."""
    from lightstage.training.config import load_config

    for name in ("cpu", "fast"):
        assert load_config(name).loss.epsilon_of_level == pytest.approx(0.028)
    paper = load_config("paper").loss
    assert paper.epsilon_of_level is None and paper.epsilon == pytest.approx(1e-3)
