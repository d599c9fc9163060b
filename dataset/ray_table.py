"""Rays of compact shard records, recomputed where they are used: the calibrated camera of each training view and
the light table of each group (both in the shard manifest) turn (view, light, pixel) into the origin, unit
direction, light position and light direction of a ray, vectorised in torch on the device that trains.

The arithmetic mirrors `lightstage.cameras.pixel_rays` (after `undistort_pixels`, OpenCV's `undistortPoints` with
its default five iterations) in float64, rounded to float32 at the end, so the rays equal those the shard stage
stored in the 64-byte format (`shard_rays.view_rays`): tests/test_ray_table.py checks them bit for bit.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from lightstage.cameras import camera_center
from lightstage.errors import LightstageError
from lightstage.records.shards import flags_flare, flags_saturated, flags_zone

UNDISTORT_ITERATIONS = 5  # cv2.undistortPoints without criteria: TermCriteria(COUNT, 5, 0.01)


def _dot3(a: tuple[torch.Tensor, ...], b: tuple[torch.Tensor, ...]) -> torch.Tensor:
    """(a0 b0 + a1 b1) + a2 b2, one rounding per operation (the order numpy's row-times-matrix products use)."""
    return (a[0] * b[0] + a[1] * b[1]) + a[2] * b[2]


def undistort(
    u: torch.Tensor, v: torch.Tensor, K: torch.Tensor, dist: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Continuous pixel coordinates (N,) of distorted OpenCV cameras (per-ray K (N, 3, 3), dist (N, 5) =
    k1 k2 p1 p2 k3) -> where the ideal pinhole camera K sees the same rays: OpenCV's iterative undistortion
    (float64), step for step, so the result equals cv2.undistortPoints(..., P=K)."""
    fx, fy, cx, cy = K[:, 0, 0], K[:, 1, 1], K[:, 0, 2], K[:, 1, 2]
    ifx, ify = 1.0 / fx, 1.0 / fy
    k1, k2, p1, p2, k3 = dist.unbind(1)
    x0 = x = (u - cx) * ifx
    y0 = y = (v - cy) * ify
    done = torch.zeros_like(u, dtype=torch.bool)
    for _ in range(UNDISTORT_ITERATIONS):
        r2 = x * x + y * y
        icdist = 1.0 / (1 + ((k3 * r2 + k2) * r2 + k1) * r2)
        done = done | (icdist < 0)  # OpenCV stops there and keeps the undistorted start
        dx = 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
        dy = p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
        x = torch.where(done, x0, (x0 - dx) * icdist)
        y = torch.where(done, y0, (y0 - dy) * icdist)
    return (fx * x + K[:, 0, 1] * y) + cx, fy * y + cy


class RayTable:
    """The cameras and lights of a shard manifest as tensors on one device; `rays(view, light, pixel)` and
    `expand(compact batch)` compute the rays of compact records there."""

    def __init__(self, manifest: dict[str, Any], device: torch.device | str = "cpu") -> None:
        cams = manifest.get("cameras")
        if not cams or len(cams) != len(manifest["views"]):
            raise LightstageError(
                "shard manifest lacks the camera table; rerun `lightstage shard WORK --force`"
            )
        f64 = torch.float64
        K = np.array([c["K"] for c in cams], np.float64).reshape(-1, 3, 3)
        R = np.array([c["R"] for c in cams], np.float64).reshape(-1, 3, 3)
        t = np.array([c["t"] for c in cams], np.float64).reshape(-1, 3)
        dist = np.zeros((len(cams), 5))
        for i, c in enumerate(cams):
            d = np.asarray(c["dist"], np.float64).reshape(-1)
            if d.size > 5 and np.any(d[5:] != 0):
                raise LightstageError(
                    f"view {manifest['views'][i]}: only k1 k2 p1 p2 k3 distortion is supported"
                )
            dist[i, : min(5, d.size)] = d[:5]
        groups = sorted(manifest["lights"])
        group_of = {g: k for k, g in enumerate(groups)}
        self.device = torch.device(device)
        self.K = torch.from_numpy(K).to(self.device, f64)
        self.Kinv = torch.from_numpy(np.linalg.inv(K)).to(self.device, f64)
        self.R = torch.from_numpy(R).to(self.device, f64)
        self.dist = torch.from_numpy(dist).to(self.device, f64)
        self.distorted = torch.from_numpy(np.any(dist != 0, axis=1)).to(self.device)
        centres = np.stack([camera_center(r, x) for r, x in zip(R, t, strict=True)]).astype(np.float32)
        self.centre = torch.from_numpy(centres).to(self.device)
        self.group = torch.tensor([group_of[v.split("/")[0]] for v in manifest["views"]], device=self.device)
        lights = [manifest["lights"][g] for g in groups]
        n = max(len(x["positions"]) for x in lights)
        pos, dirs = np.zeros((len(groups), n, 3), np.float32), np.zeros((len(groups), n, 3), np.float32)
        for k, x in enumerate(lights):
            pos[k, : len(x["positions"])] = np.asarray(x["positions"], np.float64)
            dirs[k, : len(x["directions"])] = np.asarray(x["directions"], np.float64)
        self.light_positions = torch.from_numpy(pos).to(self.device)
        self.light_directions = torch.from_numpy(dirs).to(self.device)

    def rays(
        self, view: torch.Tensor, light: torch.Tensor, pixel: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """float32 (origins, directions, light positions, light directions), each (N, 3), of rays through the
        centres of integer pixels (N, 2) = (i, j) of views (N,) under lights (N,)."""
        view, light = view.to(self.device, torch.int64), light.to(self.device, torch.int64)
        uv = pixel.to(self.device, torch.float64) + 0.5
        u, v = uv[:, 0], uv[:, 1]
        if bool(self.distorted.any()):
            sel = torch.nonzero(self.distorted[view]).squeeze(1)
            if len(sel):
                uu, vv = undistort(u[sel], v[sel], self.K[view[sel]], self.dist[view[sel]])
                u, v = u.index_put((sel,), uu), v.index_put((sel,), vv)
        Ki = self.Kinv[view]
        one = torch.ones_like(u)
        cam = [_dot3((u, v, one), (Ki[:, r, 0], Ki[:, r, 1], Ki[:, r, 2])) for r in range(3)]
        R = self.R[view]
        world = [_dot3(cam, (R[:, 0, c], R[:, 1, c], R[:, 2, c])) for c in range(3)]
        norm = torch.sqrt(_dot3(world, world))
        directions = (torch.stack(world, 1) / norm[:, None]).to(torch.float32)
        g = self.group[view]
        return self.centre[view], directions, self.light_positions[g, light], self.light_directions[g, light]

    def expand(
        self, records: torch.Tensor, normalization: dict[str, Any] | None = None
    ) -> dict[str, torch.Tensor]:
        """Compact records as int16 (B, 8) (RAY_DTYPE's bytes: rgb halves, flags, pixel, view, light) -> the
        trainer's batch dict (BATCH_KEYS) on this table's device; `normalization` {centre, scale} maps origins and
        light positions to the unit cube."""
        r = records.to(self.device, non_blocking=True)
        ids = r[:, 6:8].to(torch.int64) & 0xFFFF  # view, light: unsigned 16-bit
        o, d, lp, ld = self.rays(ids[:, 0], ids[:, 1], r[:, 4:6])
        flags = r[:, 3]
        if normalization is not None:
            c = torch.tensor(normalization["centre"], dtype=torch.float32, device=self.device)
            s = normalization["scale"]
            o, lp = (o - c) / s, (lp - c) / s
        return {
            "origins": o,
            "directions": d,
            "light_positions": lp,
            "light_directions": ld,
            "rgb": r[:, 0:3].view(torch.float16).to(torch.float32),
            "saturated": flags_saturated(flags),
            "zone": flags_zone(flags),
            "flare": flags_flare(flags),
        }
