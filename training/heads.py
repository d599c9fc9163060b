"""Output activations shared by every field: density (softplus/relu) and the exp transfer-gradient head."""

from __future__ import annotations

import torch
import torch.nn.functional as F


def density_activation(raw: torch.Tensor, kind: str, bias: float) -> torch.Tensor:
    """Non-negative density sigma from the raw network output (computed in float32)."""
    raw = raw.float() + bias
    return F.softplus(raw) if kind == "softplus" else F.relu(raw)


def exp_head(raw: torch.Tensor, max_exponent: float) -> torch.Tensor:
    """Non-negative, finite transfer gradient h = exp(min(raw, max_exponent)) in float32 (RawNeRF's exp)."""
    return torch.exp(torch.clamp(raw.float(), max=max_exponent))
