"""Scene bounds on a simulated capture against its ground-truth geometry: the carved box contains the object
and the part of the stand the cameras see, and is at most 1.3x that true visible extent along every axis."""

from __future__ import annotations

import json
import shutil

import cv2
import numpy as np

from lightstage.dataset.bounds import BoundsConfig, load_bounds, run_bounds
from lightstage.records.calibration import Calibration
from lightstage.workdir import WorkDir


def _visible_stand_z(calib: Calibration, stand: dict, min_views: int) -> float:
    """Lowest z of the stand's surface that projects inside the frame of at least `min_views` views."""
    zs = np.linspace(stand["z_min"], stand["z_max"], 600)
    ang = np.linspace(0, 2 * np.pi, 48, endpoint=False)
    cx, cy = stand["centre_xy"]
    r = stand["radius"]
    pts = np.array([[cx + r * np.cos(a), cy + r * np.sin(a), z] for z in zs for a in ang])
    count = np.zeros(len(pts), int)
    for rec in calib.views.values():
        cam = rec.camera()
        xc = pts @ cam.R.T + cam.t
        uv = xc[:, :2] / xc[:, 2:] * np.diag(cam.K)[:2] + cam.K[:2, 2]
        inside = (uv[:, 0] >= 0) & (uv[:, 0] < cam.width) & (uv[:, 1] >= 0) & (uv[:, 1] < cam.height)
        count += (xc[:, 2] > 0) & inside
    return float(pts[count >= min_views, 2].min())


def test_bounds_hold_the_object_and_visible_stand_tightly(tiny_capture, tmp_path):
    gt = tiny_capture / "ground_truth"
    work = WorkDir.at(tmp_path / "work")
    work.calibration.parent.mkdir(parents=True)
    shutil.copy(gt / "geometry.json", work.calibration)
    calib = Calibration.load(work.calibration)
    for view, rec in calib.views.items():  # ground-truth masks at the processed resolution
        cam = rec.camera()
        raw = cv2.imread(str(gt / "masks" / view.group / f"{view.camera}.png"), cv2.IMREAD_GRAYSCALE)
        small = cv2.resize(
            raw.astype(np.float32) / 255, (cam.width, cam.height), interpolation=cv2.INTER_AREA
        )
        work.mask(view).parent.mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(work.mask(view)), ((small > 0.5) * 255).astype(np.uint8))
    cfg = BoundsConfig()
    run_bounds(work, cfg, progress=False)
    b = load_bounds(work.bounds)
    scene = json.loads((gt / "scene.json").read_text())
    lo, hi = np.array(scene["object_bbox"]["min"]), np.array(scene["object_bbox"]["max"])
    lo[2] = min(lo[2], _visible_stand_z(calib, scene["stand"], cfg.min_views))
    r = scene["stand"]["radius"]
    lo[:2] = np.minimum(lo[:2], np.array(scene["stand"]["centre_xy"]) - r)
    hi[:2] = np.maximum(hi[:2], np.array(scene["stand"]["centre_xy"]) + r)
    voxel = (b.box_max - b.box_min) / cfg.resolution
    assert np.all(b.box_min <= lo + voxel) and np.all(b.box_max >= hi - voxel), (b.box_min, b.box_max, lo, hi)
    assert np.all(b.box_max - b.box_min <= 1.3 * (hi - lo)), (b.box_max - b.box_min, hi - lo)
    # the normalisation follows the tight box: its longest half-side, plus the margin
    assert np.isclose(b.scale, 0.5 * np.max(b.box_max - b.box_min) * (1 + cfg.margin))
