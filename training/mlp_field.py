"""The paper's field (Sec. 3.4): NeRF MLPs giving density sigma(x) and transfer gradient h(x; view; light).

Two forms, chosen by `model.mlp.h_mlp` (RelightModel builds one field for the coarse and one for the fine
level, so each form exists twice):

* `separate` (the paper, `paper.yaml`): "8 fully-connected layers (with a width of 256, and a skip connection
  in the fourth layer) each for the density as well as the transfer vector gradient prediction respectively".
  The density MLP sees PE(x) only: `depth` x `width` ReLU layers, PE(x) concatenated to the `skip`-th layer's
  activation (the input of layer index `skip`), then a linear sigma output. The transfer-gradient MLP is a
  second, independent network of `h_depth` x `h_width` ReLU layers (skip at `h_skip` the same way) whose input
  is exactly [PE(x, pos_freqs), PE(view, dir_freqs), PE(light, light_freqs)] (positions in the normalised unit
  cube, unit directions), followed by a linear 3-channel output through the exp activation. It does *not*
  receive the density MLP's features: Sec. 3.4 gives each prediction its own 8-layer MLP and describes no
  shared feature; both MLPs are trained jointly through the volume-rendering weights only.
* `head` (`paper-lite`, `tiny`): one `depth` x `width` trunk on PE(x) gives sigma and a `width` feature; a
  small head of `head_depth` x `head_width` on [feature, PE(view), PE(light)] gives h (NeRF's colour-head layout).
"""

from __future__ import annotations

import torch
from torch import nn

from lightstage.training.config import ModelConfig
from lightstage.training.encoding import encoded_dim, positional_encoding
from lightstage.training.heads import density_activation, exp_head


class SkipMLP(nn.ModuleList):
    """`depth` ReLU layers of `width` on an input of `in_dim`; the input is concatenated to the activation of
    layer `skip` (i.e. fed again into layer index `skip`; 0 disables). Returns the last activation. A ModuleList
    of the Linear layers, so parameter names are `<name>.<i>.weight` (as in checkpoints written before it)."""

    def __init__(self, in_dim: int, depth: int, width: int, skip: int):
        dims_in = [in_dim] + [width + (in_dim if i == skip else 0) for i in range(1, depth)]
        super().__init__(nn.Linear(d, width) for d in dims_in)
        self.skip = skip

    def forward(self, inp: torch.Tensor) -> torch.Tensor:
        h = inp
        for i, layer in enumerate(self):
            if i == self.skip and i > 0:
                h = torch.cat([h, inp], dim=-1)
            h = torch.relu(layer(h))
        return h


class MLPField(nn.Module):
    """Density MLP `trunk` on PE(x) with a linear `sigma` output; h from `h_mlp` + `h_out` (separate form) or
    from `feature` + `head` on the trunk (head form). See the module docstring for what enters each."""

    def __init__(self, cfg: ModelConfig):
        super().__init__()
        m = cfg.mlp
        self.cfg = cfg
        self.separate = m.h_mlp == "separate"
        pos_dim = encoded_dim(m.pos_freqs)
        dirs_dim = encoded_dim(m.dir_freqs) + encoded_dim(m.light_freqs)
        self.trunk = SkipMLP(pos_dim, m.depth, m.width, m.skip)
        self.sigma = nn.Linear(m.width, 1)
        if self.separate:
            self.h_mlp = SkipMLP(pos_dim + dirs_dim, m.h_depth, m.h_width, m.h_skip)
            self.h_out = nn.Linear(m.h_width, 3)
            nn.init.constant_(self.h_out.bias, cfg.h_bias_init)
        else:
            self.feature = nn.Linear(m.width, m.width)
            head_in = m.width + dirs_dim
            layers: list[nn.Module] = []
            for i in range(max(1, m.head_depth)):
                layers += [nn.Linear(head_in if i == 0 else m.head_width, m.head_width), nn.ReLU()]
            self.head = nn.Sequential(*layers, nn.Linear(m.head_width, 3))
            nn.init.constant_(self.head[-1].bias, cfg.h_bias_init)

    def _sigma(self, t: torch.Tensor) -> torch.Tensor:
        return density_activation(self.sigma(t)[..., 0], self.cfg.density_activation, self.cfg.density_bias)

    def density(self, x: torch.Tensor) -> torch.Tensor:
        """(N,) density at normalised positions (N, 3) (the density MLP only)."""
        return self._sigma(self.trunk(positional_encoding(x, self.cfg.mlp.pos_freqs)))

    def forward(
        self, x: torch.Tensor, view: torch.Tensor, light: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """(sigma (N,), h (N, 3)) at normalised positions x with unit view and light directions (N, 3)."""
        m = self.cfg.mlp
        enc = positional_encoding(x, m.pos_freqs)
        t = self.trunk(enc)
        dirs = [positional_encoding(view, m.dir_freqs), positional_encoding(light, m.light_freqs)]
        if self.separate:
            raw = self.h_out(self.h_mlp(torch.cat([enc, *dirs], -1)))
        else:
            raw = self.head(torch.cat([self.feature(t), *dirs], -1))
        return self._sigma(t), exp_head(raw, self.cfg.h_max_exponent)
