"""OLAT images of one camera under many lights at the cost of one density pass: the sample positions, densities,
volume weights and geometry features of a ray do not depend on the light (paper Eq. 1: only the transfer
gradient h sees it), so they are computed once per ray chunk and only the light-dependent transfer stage runs
per light. Used by the viewer's model basis and `lightstage relight --lights stage`.

The result equals `model.render_rays` light by light (same samples, same skipping rules; tested); a field
without a separate transfer stage (the MLP field) falls back to one full render per light.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch

from lightstage.cameras import camera_rays
from lightstage.training.encoding import encoded_dim, positional_encoding
from lightstage.training.heads import exp_head
from lightstage.training.light_model import point_light
from lightstage.training.render import volume_weights
from lightstage.training.sampling import merge_edges, midpoints, ray_box, resample_edges, stratified_edges


def render_olat_basis(
    model,
    camera,
    directions: np.ndarray,
    chunk: int = 32768,
    on_chunk: Callable[[int], None] | None = None,
) -> np.ndarray:
    """(L, H, W, 3) float32 white-light OLAT images of `camera` for L unit light `directions` (world frame).
    `model` is a TrainedModel (or anything with `render_rays`); `on_chunk(rays_done)` reports progress."""
    dirs = np.asarray(directions, np.float32).reshape(-1, 3)
    o, d = camera_rays(camera)
    net = getattr(model, "model", None)
    shared = net is not None and hasattr(net.fine, "transfer") and hasattr(net.fine, "geometry")
    device = net.centre.device if net is not None else torch.device("cpu")
    o_t = torch.from_numpy(o.astype(np.float32)).to(device)
    d_t = torch.from_numpy(d.astype(np.float32)).to(device)
    lights = torch.from_numpy(dirs).to(device)
    out = np.zeros((len(dirs), len(o), 3), np.float32)
    with torch.no_grad():
        for i in range(0, len(o), chunk):
            sl = slice(i, i + chunk)
            if shared:
                rgb = _shared_chunk(net, o_t[sl], d_t[sl], lights)
            else:
                n = len(o_t[sl])
                rgb = torch.stack(
                    [
                        torch.as_tensor(model.render_rays(o_t[sl], d_t[sl], light.expand(n, 3))).float()
                        for light in lights
                    ]
                )
            out[:, sl] = rgb.cpu().numpy()
            if on_chunk is not None:
                on_chunk(min(i + chunk, len(o)))
    return out.reshape(len(dirs), camera.height, camera.width, 3)


def _shared_chunk(net, origins: torch.Tensor, directions: torch.Tensor, lights: torch.Tensor) -> torch.Tensor:
    """(L, R, 3) pixels of R rays under L lights: RelightModel.forward's sampling, one geometry pass, L transfer
    passes (the same keep / min_weight rules as RelightModel._march and _march_two_stage)."""
    o = net.normalise(origins.float())
    d = torch.nn.functional.normalize(directions.float(), dim=-1)
    lights = torch.nn.functional.normalize(lights.float(), dim=-1)
    near, far = ray_box(o, d, net.box[0], net.box[1])
    cfg = net.cfg
    if net.coarse is not None:
        edges_c = stratified_edges(near, far, cfg.n_coarse, False)
        w_c = _weights(net, net.coarse, o, d, edges_c)[0]
        edges = merge_edges(edges_c, resample_edges(edges_c, w_c, cfg.n_fine, False, cfg.resample_padding))
    else:
        edges = stratified_edges(near, far, cfg.n_fine, False)
    w, keep, feat, x = _weights(net, net.fine, o, d, edges)
    active = keep & (w > cfg.min_weight) if cfg.min_weight > 0 else keep
    if not bool(active.any()):  # as RelightModel: one sample takes part
        active = active.clone()
        active.view(-1)[int(keep.view(-1).nonzero()[0])] = True
    rows = active.nonzero(as_tuple=True)[0]
    if getattr(net.cfg, "light", "distant") == "point" and bool(torch.isfinite(net.light_radius)):
        transfer = _point_transfer(net, feat[active[keep]], d, rows, x[active])
    else:
        transfer = FactoredTransfer.of(net.fine, feat[active[keep]], d[rows])
    weight = w[active][:, None]
    out = torch.zeros(len(lights), len(o), 3, device=o.device)
    for i, light in enumerate(lights):
        out[i].index_add_(0, rows, weight * transfer(light))
    return out


def _point_transfer(net, feat: torch.Tensor, d: torch.Tensor, rows: torch.Tensor, x: torch.Tensor):
    """`light (3,) -> h (N, 3)` for a model with point lights (`model.light: point`): the light at
    c + R ω, its direction and falloff per sample, as RelightModel._lights."""
    radius = float(net.light_radius / net.scale)

    def transfer(light: torch.Tensor) -> torch.Tensor:
        lp = net.normalise(net.light_centre + net.light_radius * light)
        dirs, fall = point_light(x, lp, radius)
        h = net.fine.transfer(feat, d, dirs, rows=rows)
        return h * fall[:, None] if net.cfg.light_falloff else h

    return transfer


class FactoredTransfer:
    """The hash-grid field's transfer stage for many lights at fixed samples. Its first layer is linear in
    [features, PE(view), PE(light), PE(half)], so the feature and view terms are computed once and the light
    term is one vector per light; only the half-vector term and the later layers run per light (about half the
    work of `field.transfer`). `of` checks it against `field.transfer` and falls back to it on a mismatch
    (a changed head layout)."""

    def __init__(self, field, feat: torch.Tensor, view: torch.Tensor):
        g = field.cfg.hashgrid
        self.field, self.feat, self.view, self.g = field, feat, view, g
        first = field.head[0]
        nf, nv, nl = feat.shape[1], encoded_dim(g.dir_freqs), encoded_dim(g.light_freqs)
        w = first.weight
        self.w_light = w[:, nf + nv : nf + nv + nl]
        self.w_half = w[:, nf + nv + nl :] if g.half_freqs >= 0 else None
        self.base = torch.addmm(
            first.bias, torch.cat([feat, positional_encoding(view, g.dir_freqs)], -1), w[:, : nf + nv].t()
        )
        # the later layers, Linear weights transposed once; ReLUs run in place on the fresh activations
        self.rest = [
            (m, m.weight.t().contiguous()) if isinstance(m, torch.nn.Linear) else (m, None)
            for m in field.head[1:]
        ]

    @classmethod
    def of(cls, field, feat: torch.Tensor, view: torch.Tensor):
        """A per-light transfer function `light (3,) -> h (N, 3)` for samples `feat` seen along `view`."""
        plain = lambda light: field.transfer(feat, view, light.expand(len(view), 3))  # noqa: E731
        if not hasattr(field.cfg, "hashgrid") or not hasattr(field, "head") or len(view) == 0:
            return plain
        try:
            fast = cls(field, feat, view)
            probe = torch.nn.functional.normalize(torch.tensor([0.3, -0.5, 0.8], device=view.device), dim=0)
            n = min(len(view), 256)
            ok = torch.allclose(fast(probe)[:n], field.transfer(feat[:n], view[:n], probe.expand(n, 3)),
                                rtol=1e-4, atol=1e-6)  # fmt: skip
        except (RuntimeError, IndexError, AttributeError):
            ok = False
        return fast if ok else plain

    def __call__(self, light: torch.Tensor) -> torch.Tensor:
        g = self.g
        pre = self.base + positional_encoding(light[None], g.light_freqs) @ self.w_light.t()
        if self.w_half is not None:
            half = torch.nn.functional.normalize(light[None] - self.view, dim=-1)
            pre = torch.addmm(pre, positional_encoding(half, g.half_freqs), self.w_half.t())
        for module, weight_t in self.rest:
            if weight_t is not None:
                pre = torch.addmm(module.bias, pre, weight_t)
            elif isinstance(module, torch.nn.ReLU):
                pre = torch.relu_(pre)
            else:
                pre = module(pre)
        return exp_head(pre, self.field.cfg.h_max_exponent)


def _weights(net, field, o: torch.Tensor, d: torch.Tensor, edges: torch.Tensor):
    """(volume weights (R, S), kept-sample mask (R, S), geometry features of the kept samples or None)."""
    t, delta = midpoints(edges)
    x = o[:, None, :] + d[:, None, :] * t[..., None]
    keep = delta > 0
    if net.occupancy is not None:
        keep = keep & net.occupancy.occupied(x)
    if not bool(keep.any()):
        keep = keep.clone()
        keep.view(-1)[0] = True
    if hasattr(field, "geometry"):
        s, feat = field.geometry(x[keep])
    else:
        s, feat = field.density(x[keep]), None
    sigma = torch.zeros(keep.shape, device=x.device, dtype=s.dtype).masked_scatter(keep, s)
    return volume_weights(sigma, delta), keep, feat, x
