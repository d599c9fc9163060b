"""The paper's field (Sec. 3.4): a NeRF MLP giving density sigma(x) and transfer gradient h(x; view; light)."""

from __future__ import annotations

import torch
from torch import nn

from lightstage.training.config import ModelConfig
from lightstage.training.encoding import encoded_dim, positional_encoding
from lightstage.training.heads import density_activation, exp_head


class MLPField(nn.Module):
    """`depth` x `width` ReLU trunk on the encoded position (re-injected before layer `skip`), a density
    output, and a head on [trunk feature, encoded view direction, encoded light direction] giving exp(h)."""

    def __init__(self, cfg: ModelConfig):
        super().__init__()
        m = cfg.mlp
        self.cfg = cfg
        in_dim = encoded_dim(m.pos_freqs)
        dims_in = [in_dim] + [m.width + (in_dim if i == m.skip else 0) for i in range(1, m.depth)]
        self.trunk = nn.ModuleList(nn.Linear(d, m.width) for d in dims_in)
        self.sigma = nn.Linear(m.width, 1)
        self.feature = nn.Linear(m.width, m.width)
        head_in = m.width + encoded_dim(m.dir_freqs) + encoded_dim(m.light_freqs)
        layers: list[nn.Module] = []
        for i in range(max(1, m.head_depth)):
            layers += [nn.Linear(head_in if i == 0 else m.head_width, m.head_width), nn.ReLU()]
        self.head = nn.Sequential(*layers, nn.Linear(m.head_width, 3))
        nn.init.constant_(self.head[-1].bias, cfg.h_bias_init)

    def _trunk(self, x: torch.Tensor) -> torch.Tensor:
        enc = positional_encoding(x, self.cfg.mlp.pos_freqs)
        h = enc
        for i, layer in enumerate(self.trunk):
            if i == self.cfg.mlp.skip and i > 0:
                h = torch.cat([h, enc], dim=-1)
            h = torch.relu(layer(h))
        return h

    def density(self, x: torch.Tensor) -> torch.Tensor:
        """(N,) density at normalised positions (N, 3)."""
        raw = self.sigma(self._trunk(x))[..., 0]
        return density_activation(raw, self.cfg.density_activation, self.cfg.density_bias)

    def forward(
        self, x: torch.Tensor, view: torch.Tensor, light: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """(sigma (N,), h (N, 3)) at normalised positions x with unit view and light directions (N, 3)."""
        m = self.cfg.mlp
        t = self._trunk(x)
        sigma = density_activation(self.sigma(t)[..., 0], self.cfg.density_activation, self.cfg.density_bias)
        head_in = torch.cat(
            [
                self.feature(t),
                positional_encoding(view, m.dir_freqs),
                positional_encoding(light, m.light_freqs),
            ],
            -1,
        )
        return sigma, exp_head(self.head(head_in), self.cfg.h_max_exponent)
