"""A small synthetic work directory (stage, nominal calibration, sphere masks and zone maps, RGBS frames) for
tests and benchmarks of split / bounds / shard / loader, without the simulator, preprocess or calibration."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from lightstage.capture.layout import CaptureInfo, save_capture_info
from lightstage.capture.presets import make_stage
from lightstage.capture.stage import Stage
from lightstage.frames import write_exr
from lightstage.ids import FrameId, ViewId
from lightstage.records.calibration import Calibration, ViewCalibration
from lightstage.workdir import DOWNSCALE, ZONE_BACKGROUND, ZONE_BAND, ZONE_FOREGROUND, WorkDir

SPHERE_CENTRE = np.array([0.02, -0.01, 0.03])
SPHERE_RADIUS = 0.1


def sphere_mask(cam, centre: np.ndarray = SPHERE_CENTRE, radius: float = SPHERE_RADIUS) -> np.ndarray:
    """(H, W) bool: pixel-centre rays of a processed camera that hit the sphere."""
    from lightstage.cameras import pixel_centers, pixel_rays

    o, d = pixel_rays(pixel_centers(cam.width, cam.height), cam.K, cam.R, cam.t)
    oc = o - centre
    b = np.sum(oc * d, axis=-1)
    c = np.sum(oc * oc, axis=-1) - radius**2
    return b * b - c >= 0


def zone_map(mask: np.ndarray, band_px: int = 2) -> np.ndarray:
    """Zones from a mask: a band of +-band_px around the silhouette, foreground inside it, background outside."""
    import cv2

    k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * band_px + 1, 2 * band_px + 1))
    m = mask.astype(np.uint8)
    band = (cv2.dilate(m, k) > 0) & ~(cv2.erode(m, k) > 0)
    z = np.full(mask.shape, ZONE_BACKGROUND, np.uint8)
    z[mask] = ZONE_FOREGROUND
    z[band] = ZONE_BAND
    return z


def make_synthetic_work(
    root: str | Path,
    num_cameras: int = 4,
    num_lights: int = 12,
    num_groups: int = 2,
    width: int = 48,
    height: int = 32,
    seed: int = 0,
    camera_distance: float = 1.3,
) -> tuple[WorkDir, Stage]:
    """Write WORK (root/work) and its raw-capture stub (root/capture): processed width x height frames."""
    import cv2

    root = Path(root)
    stage = make_stage(
        "synthetic-test",
        num_cameras=num_cameras,
        num_lights=num_lights,
        width=width * DOWNSCALE,
        height=height * DOWNSCALE,
        num_groups=num_groups,
        camera_distance=camera_distance,
    )
    cap = root / "capture"
    cap.mkdir(parents=True, exist_ok=True)
    stage.save(cap / "stage.yaml")
    save_capture_info(CaptureInfo(object_name="sphere"), cap / "capture.yaml")
    work = WorkDir.at(root / "work")
    work.root.mkdir(parents=True, exist_ok=True)
    work.capture_pointer.write_text(str(cap))
    views = {}
    for g in stage.group_names:
        for c in stage.camera_ids:
            pc = stage.view_camera(g, c)
            views[ViewId(g, c)] = ViewCalibration(pc.K, pc.R, pc.t, pc.width, pc.height)
    calib = Calibration(
        "nominal",
        views,
        {g: stage.light_positions_world(g) for g in stage.group_names},
        stage.axis,
        {g.name: g.yaw_deg for g in stage.groups},
    )
    calib.save(work.calibration)
    rng = np.random.default_rng(seed)
    for v, vc in views.items():
        cam = vc.camera()
        mask = sphere_mask(cam)
        work.view_dir(v).mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(work.mask(v)), mask.astype(np.uint8) * 255)
        cv2.imwrite(str(work.zones(v)), zone_map(mask))
        for lt in range(num_lights):
            rgb = rng.gamma(2.0, 0.3, size=(height, width, 3)).astype(np.float32)
            sat = (rng.random((height, width)) < 0.02).astype(np.float32)
            rgb[sat > 0] = stage.saturation
            write_exr(work.frame(FrameId(v.group, v.camera, lt)), np.dstack([rgb, sat]), channels="RGBS")
    return work, stage


def write_random_shards(root: str | Path, num_shards: int, rays_per_shard: int, seed: int = 0) -> Path:
    """Shards of random (valid-looking) rays with a real manifest, for loader benchmarks: root/shards."""
    import json

    from lightstage.atomic import write_json_atomic
    from lightstage.cameras import look_at
    from lightstage.dataset.shards import file_sha256
    from lightstage.records.shards import (
        COMPOSITION,
        MANIFEST,
        RAY_DTYPE,
        SHARD_FORMAT_VERSION,
        ZONE_NAMES,
        ZONES,
        pack_flags,
    )

    VIEWS, LIGHTS = ("000/cam00", "000/cam01", "040/cam00", "040/cam01"), 331
    rng = np.random.default_rng(seed)
    cameras = []
    for k in range(len(VIEWS)):
        R, t = look_at(np.array([2.0 * np.cos(k), 2.0 * np.sin(k), 0.5]), np.zeros(3))
        K = [[1800.0, 0.0, 1024.0], [0.0, 1800.0, 683.0], [0.0, 0.0, 1.0]]
        cameras.append(
            {"K": K, "R": R.tolist(), "t": t.tolist(), "dist": [0.0] * 5, "width": 2048, "height": 1366}
        )
    dirs = rng.standard_normal((LIGHTS, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    lights = {g: {"positions": (1.5 * dirs).tolist(), "directions": dirs.tolist()} for g in ("000", "040")}

    out = Path(root) / "shards"
    (out / "train").mkdir(parents=True, exist_ok=True)
    per = [rays_per_shard // 8 * c for c in COMPOSITION]
    records = []
    for s in range(num_shards):
        a = np.zeros(rays_per_shard, RAY_DTYPE)
        a["rgb"] = rng.random((rays_per_shard, 3), dtype=np.float32)
        a["flags"] = pack_flags(rng.random(rays_per_shard) < 0.02, np.repeat(np.array(ZONES, np.uint8), per))
        a["pixel"] = rng.integers(-16, 2048, (rays_per_shard, 2))
        a["view"] = rng.integers(0, len(VIEWS), rays_per_shard)
        a["light"] = rng.integers(0, LIGHTS, rays_per_shard)
        path = out / "train" / f"shard_{s:05d}.npy"
        np.save(path, a)
        records.append(
            {
                "file": f"train/{path.name}",
                "rays": rays_per_shard,
                "zones": {ZONE_NAMES[z]: n for z, n in zip(ZONES, per, strict=True)},
                "sha256": file_sha256(path),
                "bytes": path.stat().st_size,
            }
        )
    write_json_atomic(
        out / MANIFEST,
        {
            "format_version": SHARD_FORMAT_VERSION,
            "dtype": {"descr": str(RAY_DTYPE.descr), "itemsize": RAY_DTYPE.itemsize},
            "rays": num_shards * rays_per_shard,
            "rays_per_shard": rays_per_shard,
            "normalization": {"centre": [0.0, 0.0, 0.0], "scale": 1.0},
            "views": list(VIEWS),
            "cameras": cameras,
            "lights": lights,
            "shards": records,
            "note": json.dumps({"synthetic": True}),
        },
    )
    return out
