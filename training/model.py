"""The relighting model: coarse + fine fields volume-rendered inside the normalised scene bounds (paper Sec. 3),
or one hash-grid field with an occupancy grid (`fast`), chosen by `ModelConfig`.

World rays are mapped into the unit cube with x_norm = (x - centre) / scale (directions unchanged, lengths in
normalised units); samples lie between the ray's entry and exit of the scene box (the carved visual hull's box,
in normalised coordinates inside [-1, 1]^3; the whole cube when none is given), and rays that miss render 0.
"""

from __future__ import annotations

import torch
from torch import nn

from lightstage.training.config import ModelConfig
from lightstage.training.hashgrid import HashGridField
from lightstage.training.light_model import point_light
from lightstage.training.mlp_field import MLPField
from lightstage.training.occupancy import OccupancyGrid, box_cells, density_threshold, hull_prior
from lightstage.training.render import composite, composite_rows, volume_weights
from lightstage.training.sampling import merge_edges, midpoints, ray_box, resample_edges, stratified_edges


def make_field(cfg: ModelConfig) -> nn.Module:
    """The field named by `cfg.field`."""
    return MLPField(cfg) if cfg.field == "mlp" else HashGridField(cfg)


class RelightModel(nn.Module):
    """forward(origins, directions, light_directions) in world coordinates -> dict with the HDR pixel `rgb` (R, 3),
    the fine densities `sigma` (R, S), and `rgb_coarse` / `sigma_coarse` when a coarse field exists."""

    def __init__(
        self,
        cfg: ModelConfig,
        centre: torch.Tensor | list[float],
        scale: float,
        box: torch.Tensor | list | None = None,
        hull: torch.Tensor | None = None,
    ):
        """`box`: (2, 3) world min / max corners that samples are confined to (None: the whole unit cube);
        `hull`: bool voxels tiling the box (the carved visual hull), the occupancy grid's starting prior."""
        super().__init__()
        self.cfg = cfg
        self.register_buffer("centre", torch.as_tensor(centre, dtype=torch.float32).reshape(3).clone())
        self.register_buffer("scale", torch.tensor(float(scale), dtype=torch.float32))
        if box is None:
            norm_box = torch.tensor([[-1.0] * 3, [1.0] * 3])
        else:
            norm_box = self.normalise(torch.as_tensor(box, dtype=torch.float32).reshape(2, 3))
        self.register_buffer("box", norm_box.clamp(-1.0, 1.0))
        self.coarse = make_field(cfg) if cfg.n_coarse > 0 else None
        self.fine = make_field(cfg)
        self.occupancy = None
        if cfg.occupancy.enabled:
            first_pass = cfg.n_coarse if cfg.n_coarse > 0 else cfg.n_fine
            threshold = density_threshold(cfg.occupancy.min_alpha, first_pass)
            res = cfg.occupancy.resolution
            region = box_cells(self.box[0].cpu(), self.box[1].cpu(), res)
            self.occupancy = OccupancyGrid(res, cfg.occupancy.decay, threshold, region)
            if hull is not None and box is not None:
                prior = hull_prior(torch.as_tensor(hull), self.box[0], self.box[1], cfg.occupancy.resolution)
                self.occupancy.set_prior(prior)
        if cfg.light == "point":  # world light centre and distance (set_light_frame); inf: a distant light
            self.register_buffer("light_centre", torch.zeros(3))
            self.register_buffer("light_radius", torch.tensor(float("inf")))

    def set_light_frame(self, centre: torch.Tensor | list[float], radius: float) -> None:
        """Where ω is measured from (world) and how far the lights are (metres), for `light: point`."""
        self.light_centre.copy_(torch.as_tensor(centre, dtype=torch.float32).reshape(3))
        self.light_radius.fill_(float(radius))

    def normalise(self, points: torch.Tensor) -> torch.Tensor:
        """World points -> unit-cube coordinates."""
        return (points - self.centre) / self.scale

    def forward(
        self,
        origins: torch.Tensor,
        directions: torch.Tensor,
        light_directions: torch.Tensor,
        randomized: bool = False,
    ) -> dict[str, torch.Tensor]:
        o = self.normalise(origins.float())
        d = torch.nn.functional.normalize(directions.float(), dim=-1)
        light = torch.nn.functional.normalize(light_directions.float(), dim=-1)
        near, far = ray_box(o, d, self.box[0], self.box[1])
        if self.cfg.light == "point" and bool(torch.isfinite(self.light_radius)):
            # (light position in normalised coordinates per ray, light distance in normalised units)
            lp = self.normalise(self.light_centre + self.light_radius * light)
            light = (light, lp, float(self.light_radius / self.scale))
        out: dict[str, torch.Tensor] = {}
        if self.coarse is not None:
            edges_c = stratified_edges(near, far, self.cfg.n_coarse, randomized)
            rgb_c, sigma_c, w_c = self._march(self.coarse, o, d, light, edges_c)
            out.update(rgb_coarse=rgb_c, sigma_coarse=sigma_c)
            edges_f = resample_edges(edges_c, w_c, self.cfg.n_fine, randomized, self.cfg.resample_padding)
            edges = merge_edges(edges_c, edges_f)
        else:
            edges = stratified_edges(near, far, self.cfg.n_fine, randomized)
        rgb, sigma, w = self._march(self.fine, o, d, light, edges)
        out.update(rgb=rgb, sigma=sigma, acc=w.sum(-1))
        return out

    def _lights(
        self, light: torch.Tensor | tuple, x: torch.Tensor, rows: torch.Tensor | None
    ) -> tuple[torch.Tensor, torch.Tensor | None]:
        """(light directions, falloff or None) at samples x (N, 3) of rays `rows` (None: x is (R, S, 3), every
        sample): the per-ray ω for a distant light, per sample towards a point light (`light: point`)."""
        if not isinstance(light, tuple):
            return (light[rows] if rows is not None else light[:, None].expand(x.shape)), None
        _, lp, radius = light
        dirs, fall = point_light(x, lp[rows] if rows is not None else lp[:, None], radius)
        return dirs, (fall if self.cfg.light_falloff else None)

    def _march(
        self,
        field: nn.Module,
        o: torch.Tensor,
        d: torch.Tensor,
        light: torch.Tensor | tuple,
        edges: torch.Tensor,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Evaluate `field` at interval midpoints (skipping empty/zero-length ones) and composite."""
        t, delta = midpoints(edges)
        x = o[:, None, :] + d[:, None, :] * t[..., None]  # (R, S, 3)
        keep = delta > 0
        if self.occupancy is not None:
            keep = keep & self.occupancy.occupied(x)
        if not bool(keep.any()):  # evaluate one sample so every parameter takes part (DDP needs it)
            keep = keep.clone()
            keep.view(-1)[0] = True
        R, S = t.shape
        if hasattr(field, "geometry"):  # hash grid: geometry, then the transfer stage where it matters
            min_weight = 0.0 if torch.is_grad_enabled() else self.cfg.min_weight
            return self._march_staged(field, x, d, light, keep, delta, min_weight)
        if bool(keep.all()):
            ls, fall = self._lights(light, x, None)
            s, h = field(
                x.reshape(-1, 3),
                d[:, None].expand(R, S, 3).reshape(-1, 3),
                ls.reshape(-1, 3),
            )
            if fall is not None:
                h = h * fall.reshape(-1, 1)
            sigma, hh = s.reshape(R, S), h.reshape(R, S, 3)
        else:
            rows = keep.nonzero(as_tuple=True)[0]
            xk = x[keep]
            ls, fall = self._lights(light, xk, rows)
            s, h = field(xk, d[rows], ls)
            if fall is not None:
                h = h * fall[:, None]
            sigma = torch.zeros(R, S, device=x.device, dtype=s.dtype).masked_scatter(keep, s)
            hh = torch.zeros(R, S, 3, device=x.device, dtype=h.dtype).masked_scatter(keep[..., None], h)
        w = volume_weights(sigma, delta)
        return composite(w, hh), sigma, w

    def _march_staged(
        self,
        field: nn.Module,
        x: torch.Tensor,
        d: torch.Tensor,
        light: torch.Tensor | tuple,
        keep: torch.Tensor,
        delta: torch.Tensor,
        min_weight: float = 0.0,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Density and features at the kept samples, then the transfer stage at those whose volume weight
        exceeds `min_weight` (rendering: on a surface-like object a handful of samples per ray), else at
        all. Training (min_weight 0) never skips by weight: a skipped sample passes no gradient to its own
        density, and a region whose weights fell below the threshold could never grow back (a dark, thin
        stand is lost that way). Skipping by transmittance (behind the surface) did not pay on the demo
        capture: its trained density is volumetric (~3/4 of the kept samples carry weight > 1e-3).
        Training with a distant light on CPU runs both MLPs chunked in one function (`fused_mlp`)."""
        R, S = keep.shape
        if min_weight <= 0 and not isinstance(light, tuple) and field.fused_available(x):
            rows = keep.nonzero(as_tuple=True)[0]
            s, h = field.geometry_and_transfer(x[keep], d, light, rows)
            sigma = torch.zeros(R, S, device=x.device, dtype=s.dtype).masked_scatter(keep, s)
            w = volume_weights(sigma, delta)
            return composite_rows(w[keep], h, rows, R), sigma, w
        s, feat = field.geometry(x[keep])
        sigma = torch.zeros(R, S, device=x.device, dtype=s.dtype).masked_scatter(keep, s)
        w = volume_weights(sigma, delta)
        active = keep & (w.detach() > min_weight) if min_weight > 0 else keep
        if not bool(active.any()):  # one sample, so every parameter takes part (DDP needs it)
            active = active.clone()
            active.view(-1)[int(keep.view(-1).nonzero()[0])] = True
        if active is not keep:
            feat = feat[active[keep]]
        rows = active.nonzero(as_tuple=True)[0]
        if isinstance(light, tuple):  # point light: direction (and falloff) per sample
            ls, fall = self._lights(light, x[active], rows)
            h = field.transfer(feat, d, ls, rows=rows)
            if fall is not None:
                h = h * fall[:, None]
        else:
            h = field.transfer(feat, d, light, rows=rows, per_ray_light=True)
        hh = torch.zeros(R, S, 3, device=x.device, dtype=h.dtype).masked_scatter(active[..., None], h)
        return composite(w, hh), sigma, w

    @torch.no_grad()
    def update_occupancy(self, step: int, seed: int) -> None:
        """Refresh the occupancy grid (no-op without one or before its warm-up / between update steps)."""
        occ = self.cfg.occupancy
        if self.occupancy is None or step < occ.warmup_steps or step % occ.update_every:
            return
        self.occupancy.update(self.fine.density, seed=seed * 1_000_003 + step)

    def density(self, points_world: torch.Tensor) -> torch.Tensor:
        """(N,) fine-field density at world points; 0 outside the scene box."""
        x = self.normalise(points_world.float())
        inside = ((x >= self.box[0]) & (x <= self.box[1])).all(-1)
        return torch.where(inside, self.fine.density(x.clamp(-1.0, 1.0)), torch.zeros_like(x[:, 0]))
