"""Training losses: the RawNeRF weighted L2 on HDR pixels (one-sided on saturated targets; none on rays whose
pixel is in its frame's flare and bulb mask, batch key `flare`) and the L2 mask loss on the densities of samples
along background rays: every ray whose target pixel is outside the foreground mask, the near-silhouette band
(ZONE_BAND, outside the mask by construction) and the padded border included, as the paper puts it (its L2 on the
densities of background rays).

The weighted L2 ((y_hat - y) / (sg(y_hat) + eps))^2 approximates an L2 on log(y + eps), so eps sets the darkest
level that still counts: eps = 1e-3 assumes linear HDR where object pixels are ~0.05-1 (the preprocess scale,
saturation at 4.4); background targets are 0, for which the loss is ~1 as soon as y_hat >> eps. With
`loss.epsilon_of_level` eps is measured instead: a fraction of the training data's level (1 / exposure).
"""

from __future__ import annotations

import dataclasses

import torch

from lightstage.training.config import LossConfig
from lightstage.workdir import ZONE_FOREGROUND


def measured_epsilon(cfg: LossConfig, exposure: float) -> LossConfig:
    """`cfg` with its epsilon measured from the data when `epsilon_of_level` is set: that fraction of the
    level the exposure maps to 1 (1 / exposure), so the darkest level that counts follows the capture's scale."""
    if cfg.epsilon_of_level is None:
        return cfg
    return dataclasses.replace(cfg, epsilon=cfg.epsilon_of_level / exposure)


def weighted_l2(
    pred: torch.Tensor,
    target: torch.Tensor,
    eps: float,
    saturated: torch.Tensor | None = None,
    ignore: torch.Tensor | None = None,
) -> torch.Tensor:
    """Mean of ((pred - target) / (sg(pred) + eps))^2; where `saturated` (R,) is set, pred >= target costs nothing;
    rays where `ignore` (R,) is set (flare and bulb pixels) are left out of the mean (0 when every ray is)."""
    r = (pred - target) / (pred.detach() + eps)
    if saturated is not None:
        r = torch.where(saturated[:, None] & (pred >= target), torch.zeros_like(r), r)
    if ignore is None:
        return (r**2).mean()
    keep = (~ignore.bool()).to(r.dtype)[:, None]
    return (r**2 * keep).sum() / (keep.sum() * r.shape[1]).clamp_min(1.0)


def mask_loss(sigma: torch.Tensor, background: torch.Tensor) -> torch.Tensor:
    """Mean squared density over all samples (R, S) of background rays (R,) (0 when the batch has none)."""
    if not bool(background.any()):
        return sigma.sum() * 0.0
    return (sigma[background] ** 2).mean()


def total_loss(
    outputs: dict[str, torch.Tensor], batch: dict[str, torch.Tensor], cfg: LossConfig
) -> tuple[torch.Tensor, dict[str, float]]:
    """Weighted sum of the fine/coarse pixel losses and the mask loss; also returns each term as a float."""
    target = batch["rgb"]
    saturated = batch.get("saturated") if cfg.saturated_one_sided else None
    if saturated is not None:
        saturated = saturated.bool()
    background = batch["zone"] != ZONE_FOREGROUND  # band and background zones: target pixel outside the mask
    flare = batch.get("flare")
    parts: dict[str, torch.Tensor] = {
        "rgb_fine": weighted_l2(outputs["rgb"], target, cfg.epsilon, saturated, flare)
    }
    total = cfg.rgb_fine * parts["rgb_fine"]
    sigma_terms = [outputs["sigma"]]
    if "rgb_coarse" in outputs:
        parts["rgb_coarse"] = weighted_l2(outputs["rgb_coarse"], target, cfg.epsilon, saturated, flare)
        total = total + cfg.rgb_coarse * parts["rgb_coarse"]
        sigma_terms.append(outputs["sigma_coarse"])
    if cfg.mask > 0:
        parts["mask"] = sum(mask_loss(s, background) for s in sigma_terms) / len(sigma_terms)
        total = total + cfg.mask * parts["mask"]
    return total, {k: float(v.detach()) for k, v in parts.items()}
