"""LPIPS (VGG, v0.1 linear layers; Zhang et al. 2018) from locally supplied weights only.

Needs two files the user provides (nothing is downloaded, and a random backbone is never used): torchvision's
VGG16 ImageNet state dict (`features.N.weight/bias`) and the LPIPS package's `vgg.pth` linear layers
(`linK.model.1.weight`). Without them `lpips_or_none` returns (None, reason) and evaluation reports LPIPS as
unavailable. Not verified against the reference package here (neither the weights nor `lpips` are installable
offline); the layer taps, scaling constants and normalisation follow the reference implementation.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch
from torch import nn

# torchvision VGG16 `features` conv layer indices, and the ReLU outputs LPIPS taps (relu1_2 .. relu5_3).
VGG_CONVS = (0, 2, 5, 7, 10, 12, 14, 17, 19, 21, 24, 26, 28)
VGG_CHANNELS = (64, 64, 128, 128, 256, 256, 256, 512, 512, 512, 512, 512, 512)
POOL_AFTER = (2, 7, 14, 21)  # max-pool layer indices inside `features`
TAPS = (3, 8, 15, 22, 29)
SHIFT = (-0.030, -0.088, -0.188)
SCALE = (0.458, 0.448, 0.450)


class LPIPSVGG(nn.Module):
    """LPIPS distance between [0, 1] RGB images (N, 3, H, W)."""

    def __init__(self, vgg_state: dict[str, torch.Tensor], lin_state: dict[str, torch.Tensor]):
        super().__init__()
        layers: list[nn.Module] = []
        in_ch = 3
        convs = dict(zip(VGG_CONVS, VGG_CHANNELS, strict=True))
        for i in range(30):
            if i in convs:
                layers.append(nn.Conv2d(in_ch, convs[i], 3, padding=1))
                in_ch = convs[i]
            elif i in POOL_AFTER:
                layers.append(nn.MaxPool2d(2, 2))
            else:
                layers.append(nn.ReLU())
        self.features = nn.Sequential(*layers)
        self.features.load_state_dict(
            {k.removeprefix("features."): v for k, v in vgg_state.items() if k.startswith("features.")}
        )
        self.lins = nn.ModuleList(nn.Conv2d(c, 1, 1, bias=False) for c in (64, 128, 256, 512, 512))
        for k, lin in enumerate(self.lins):
            lin.weight.data.copy_(lin_state[f"lin{k}.model.1.weight"])
        self.register_buffer("shift", torch.tensor(SHIFT).view(1, 3, 1, 1))
        self.register_buffer("scale", torch.tensor(SCALE).view(1, 3, 1, 1))
        self.eval().requires_grad_(False)

    def _taps(self, x: torch.Tensor) -> list[torch.Tensor]:
        x = ((x * 2 - 1) - self.shift) / self.scale
        out = []
        for i, layer in enumerate(self.features):
            x = layer(x)
            if i in TAPS:
                out.append(x / (x.norm(dim=1, keepdim=True) + 1e-10))
        return out

    @torch.no_grad()
    def forward(self, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        return sum(
            lin((fa - fb) ** 2).mean((2, 3))
            for lin, fa, fb in zip(self.lins, self._taps(a), self._taps(b), strict=True)
        )[:, 0]


def lpips_or_none(vgg_path: str, lin_path: str, device: str = "cpu") -> tuple[Callable | None, str]:
    """(fn(pred01 HxWx3, target01 HxWx3) -> float, note) when both weight files exist locally, else (None, why)."""
    if not vgg_path or not lin_path:
        return (
            None,
            "unavailable: set eval.lpips_weights (torchvision VGG16) and eval.lpips_linear_weights (lpips vgg.pth)",
        )
    for p in (vgg_path, lin_path):
        if not Path(p).is_file():
            return None, f"unavailable: {p} not found"
    net = LPIPSVGG(
        torch.load(vgg_path, map_location="cpu", weights_only=True),
        torch.load(lin_path, map_location="cpu", weights_only=True),
    ).to(device)

    def fn(pred: np.ndarray, target: np.ndarray) -> float:
        t = [
            torch.from_numpy(np.ascontiguousarray(x, np.float32)).permute(2, 0, 1)[None].to(device)
            for x in (pred, target)
        ]
        return float(net(*t)[0])

    return fn, "vgg"
