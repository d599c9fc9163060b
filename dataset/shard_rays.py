"""Phase A of the shard stage: one training view's rays sampled by zone (foreground, near-silhouette band,
background plus a padded border with target 0) for every training light of the view, written as one temporary
chunk of zone blocks (dataset/shards.py gathers the chunks into shards)."""

from __future__ import annotations

import hashlib
import json
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from lightstage.atomic import atomic_path, write_json_atomic
from lightstage.dataset.shard_config import ShardConfig
from lightstage.errors import LightstageError
from lightstage.ids import FrameId, ViewId
from lightstage.records.processed import read_flare_mask, read_mask
from lightstage.records.shards import (
    COMPOSITION,
    RAY_DTYPE,
    ZONE_NAMES,
    ZONES,
    pack_flags,
)
from lightstage.workdir import ZONE_BACKGROUND, ZONE_BAND, ZONE_FOREGROUND, WorkDir


# ---- geometry --------------------------------------------------------------------------------------
def view_rays(
    K: np.ndarray, R: np.ndarray, t: np.ndarray, dist: np.ndarray, pixels: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """float32 world (origins, directions) through the centres of integer pixels (N, 2) = (i, j) of a
    processed-resolution camera; distorted cameras are undistorted first (OpenCV). The reference the loader's
    torch recomputation (lightstage.dataset.ray_table) equals bit for bit."""
    from lightstage.cameras import pixel_rays, undistort_pixels

    o, d = pixel_rays(undistort_pixels(pixels.astype(np.float64) + 0.5, K, dist), K, R, t)
    return o.astype(np.float32), d.astype(np.float32)


def border_geometry(width: int, height: int, cfg: ShardConfig) -> tuple[int, int]:
    """(pad_x, pad_y): padding in pixels on each side of the image for the background border."""
    px = py = cfg.border_px
    if cfg.pad_to_square:
        if width > height:
            py += (width - height + 1) // 2
        else:
            px += (height - width + 1) // 2
    return px, py


def border_pixels(index: np.ndarray, width: int, height: int, pad: tuple[int, int]) -> np.ndarray:
    """Integer pixels (N, 2) of the padded ring outside the image, from indices in [0, ring size)."""
    px, py = pad
    W = width + 2 * px
    top = py * W  # rows -py..-1 (all columns), then rows H..H+py-1, then side columns of the image rows
    out = np.empty((len(index), 2), np.int64)
    a = index < top
    out[a, 0] = index[a] % W - px
    out[a, 1] = index[a] // W - py
    b = (index >= top) & (index < 2 * top)
    k = index[b] - top
    out[b, 0] = k % W - px
    out[b, 1] = height + k // W
    c = index >= 2 * top
    k = index[c] - 2 * top
    row, col = k // (2 * px), k % (2 * px)
    out[c, 0] = np.where(col < px, col - px, width + col - px)
    out[c, 1] = row
    return out


def ring_size(width: int, height: int, pad: tuple[int, int]) -> int:
    px, py = pad
    return 2 * py * (width + 2 * px) + 2 * px * height


def read_frame(path: Path, size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """A processed frame: ((H, W, 3) float16 RGB as stored, (H, W) bool saturated), through preprocess's
    reader when it is installed, else lightstage.frames.read_exr on channels R, G, B, S."""
    try:
        from lightstage.records.processed import read_processed_half
    except ImportError:
        from lightstage.frames import read_exr

        img = read_exr(path, expected_size=size, channels="RGBS")
        return img[..., :3].astype(np.float16), img[..., 3] > 0.5
    return read_processed_half(path, size)


# ---- phase A: one training view -> one chunk ---------------------------------------------------------
@dataclass(frozen=True)
class ViewTask:
    """Everything a worker needs to write one view's chunk (small, picklable)."""

    work: str
    index: int  # position in the manifest's views list
    group: str
    camera: str
    lights: tuple[int, ...]
    width: int
    height: int
    config: dict
    chunk: str


def sampling_zones(mask: np.ndarray, band_fraction: float) -> np.ndarray:
    """uint8 (H, W) sampling zones: ZONE_FOREGROUND on the mask, ZONE_BAND within band_fraction * W pixels
    outside it (an outer dilation that scales with the resolution), ZONE_BACKGROUND elsewhere."""
    import cv2

    zones = np.where(mask, ZONE_FOREGROUND, ZONE_BACKGROUND).astype(np.uint8)
    width = band_fraction * mask.shape[1]
    if width > 0 and mask.any() and not mask.all():
        dist = cv2.distanceTransform((~mask).astype(np.uint8), cv2.DIST_L2, 5)
        zones[(dist > 0) & (dist <= width)] = ZONE_BAND
    return zones


def image_quotas(cfg: ShardConfig, foreground_pixels: int) -> tuple[int, int, int]:
    """(fg, band, bg) rays of one training image: the fixed `rays_per_image` in 4:3:1, or in proportion to the
    image's foreground (`foreground_fraction` of its pixels; band 3/4 and background 1/4 of that)."""
    if cfg.rays_per_image:
        return quotas(cfg.rays_per_image)
    fg = max(4, int(round(cfg.foreground_fraction * foreground_pixels)))
    return (
        fg,
        int(round(fg * COMPOSITION[1] / COMPOSITION[0])),
        int(round(fg * COMPOSITION[2] / COMPOSITION[0])),
    )


def quotas(total: int) -> tuple[int, int, int]:
    """Per-zone counts (fg, band, bg) of `total` (a multiple of 8) in the paper's 4:3:1."""
    return tuple(total // 8 * c for c in COMPOSITION)  # type: ignore[return-value]


def write_view_chunk(task: ViewTask) -> dict[str, Any]:
    """Sample every training frame of a view by zone, compute its rays, write the view's chunk (.npy)."""
    from lightstage.threads import set_library_threads

    set_library_threads(1)
    chunk = Path(task.chunk)
    meta_path = chunk.with_suffix(".json")
    if chunk.is_file() and meta_path.is_file():
        meta = json.loads(meta_path.read_text())
        if meta.get("task_hash") == _task_hash(task):
            return meta
    cfg = ShardConfig(**task.config)
    work = WorkDir.at(task.work)
    view = ViewId(task.group, task.camera)
    W, H = task.width, task.height
    mask_path = work.mask(view)
    keep_value = read_mask(mask_path)
    if keep_value.shape != (H, W):
        raise LightstageError(
            f"{mask_path}: mask is {keep_value.shape[1]}x{keep_value.shape[0]}, camera is {W}x{H}"
        )
    zones = sampling_zones(keep_value, cfg.band_fraction)
    if cfg.background_target == "pixel":
        keep_value = np.ones_like(keep_value)
    pools = {z: np.flatnonzero(zones.ravel() == z) for z in (ZONE_FOREGROUND, ZONE_BAND)}
    bg_img = np.flatnonzero(zones.ravel() == ZONE_BACKGROUND)
    pad = border_geometry(W, H, cfg)
    n_ring = ring_size(W, H, pad)
    q = dict(zip(ZONES, image_quotas(cfg, pools[ZONE_FOREGROUND].size), strict=True))
    blocks: dict[int, list[np.ndarray]] = {z: [] for z in ZONES}
    stats = {"duplicated": 0, "missing": {ZONE_NAMES[z]: 0 for z in ZONES}}
    for light in task.lights:
        frame = FrameId(task.group, task.camera, light)
        img_rgb, img_sat = read_frame(work.frame(frame), (W, H))
        flare = read_flare_mask(work.flare_mask(frame), (H, W))  # where the target is the pixel: no loss
        rng = np.random.default_rng([cfg.seed, task.index, light])
        for z in ZONES:
            if z == ZONE_BACKGROUND:
                n_pool = bg_img.size + n_ring
                if n_pool == 0:
                    stats["missing"][ZONE_NAMES[z]] += q[z]
                    continue
                sel = rng.choice(n_pool, size=q[z], replace=n_pool < q[z])
                in_img = sel < bg_img.size
                pix = np.empty((q[z], 2), np.int64)
                flat = bg_img[sel[in_img]]
                pix[in_img, 0], pix[in_img, 1] = flat % W, flat // W
                pix[~in_img] = border_pixels(sel[~in_img] - bg_img.size, W, H, pad)
            else:
                pool = pools[z]
                if pool.size == 0:
                    stats["missing"][ZONE_NAMES[z]] += q[z]
                    continue
                replace = pool.size < q[z]
                stats["duplicated"] += max(0, q[z] - pool.size) if replace else 0
                flat = pool[rng.choice(pool.size, size=q[z], replace=replace)]
                pix = np.stack([flat % W, flat // W], axis=1)
            # Rays come from the manifest's camera table where they are read.
            rec = np.zeros(len(pix), RAY_DTYPE)
            inside = (pix[:, 0] >= 0) & (pix[:, 0] < W) & (pix[:, 1] >= 0) & (pix[:, 1] < H)
            ii, jj = pix[inside, 0], pix[inside, 1]
            keep = keep_value[jj, ii]
            rgb = np.zeros((len(pix), 3), np.float16)
            rgb[inside] = np.where(keep[:, None], img_rgb[jj, ii], 0)
            sat = np.zeros(len(pix), np.uint8)
            sat[inside] = img_sat[jj, ii] & keep
            fl = np.zeros(len(pix), bool)
            fl[inside] = flare[jj, ii] & keep
            rec["rgb"], rec["flags"] = rgb, pack_flags(sat, z, fl)
            rec["view"], rec["light"], rec["pixel"] = task.index, light, pix
            blocks[z].append(rec)
    rng = np.random.default_rng([cfg.seed, task.index, 1 << 20])
    parts, counts = [], []
    for z in ZONES:
        b = np.concatenate(blocks[z]) if blocks[z] else np.zeros(0, RAY_DTYPE)
        parts.append(b[rng.permutation(len(b))])
        counts.append(len(b))
    with atomic_path(chunk) as tmp:
        np.save(tmp, np.concatenate(parts))
    meta = {"view": task.index, "counts": counts, "task_hash": _task_hash(task)} | stats
    write_json_atomic(meta_path, meta)
    return meta


def _task_hash(task: Any) -> str:
    d = asdict(task)
    d.pop("chunk", None)
    d.pop("work", None)
    return hashlib.sha256(json.dumps(d, sort_keys=True, default=str).encode()).hexdigest()[:16]
