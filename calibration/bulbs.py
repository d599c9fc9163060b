"""Light positions from the bulbs visible in the frames: saturated blobs outside the object, triangulated.

A light that a camera sees directly shows as a small clipped disc in that camera's frame of that light. Lights
and cameras are locked to the rig, so in the stage rig frame each such observation is a ray from the camera
centre towards the bulb, the same in every group (the groups only change what the object hides). Per (light,
camera) the disc centre is taken from the processed frames of the groups where the disc is whole (not touching
the object or the image border); the rays of all cameras that see the light are combined with the nominal
position as a prior (per-axis `prior_sigma`): with one camera this moves the light onto its ray (2 of 3
coordinates observed), with two or more it triangulates it. Lights never seen keep their nominal positions.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from lightstage.capture.layout import Capture, FrameId, ViewId
from lightstage.errors import LightstageError
from lightstage.workdir import DOWNSCALE, WorkDir

LUMA = np.array([0.2126, 0.7152, 0.0722], np.float32)


@dataclass
class BulbEstimate:
    """Rig-frame light positions (metres) and how each was obtained."""

    positions: np.ndarray  # (L, 3) stage rig frame
    cameras_per_light: dict[int, list[str]] = field(
        default_factory=dict
    )  # light index -> cameras that saw it
    shift_mm: dict[int, float] = field(default_factory=dict)  # light index -> distance from nominal
    frames_read: int = 0


def detect_bulb(
    rgb: np.ndarray, saturated: np.ndarray, mask: np.ndarray, saturation: float, min_area: int = 2
) -> tuple[float, float, float] | None:
    """Centre (u, v) in pixel coordinates (pixel centres at i + 0.5) and area (pixels) of the largest whole clipped
    blob outside the (dilated) object mask, or None. The coverage of each processed pixel is recovered from its
    area-averaged value between the local background and the clip level, so the centre is sub-pixel."""
    h, w = saturated.shape
    near_object = cv2.dilate(mask.astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
    blobs = saturated & ~mask
    if not blobs.any():
        return None
    n, labels, stats, _ = cv2.connectedComponentsWithStats(blobs.astype(np.uint8), connectivity=8)
    best = None
    for i in range(1, n):
        x, y, bw, bh, area = stats[i]
        if area < min_area:
            continue
        if x == 0 or y == 0 or x + bw >= w or y + bh >= h:
            continue  # cut by the image border
        if near_object[labels == i].any():
            continue  # touching the silhouette: possibly partly hidden behind the object
        if best is None or area > best[1]:
            best = (i, area)
    if best is None:
        return None
    comp = labels == best[0]
    ring = (cv2.dilate(comp.astype(np.uint8), np.ones((7, 7), np.uint8)) > 0) & ~comp & ~saturated & ~mask
    lum = rgb @ LUMA
    bg = float(np.median(lum[ring])) if ring.any() else 0.0
    top = float(saturation)
    if top <= bg:
        return None
    cover = np.clip((lum - bg) / (top - bg), 0.0, 1.0) * comp
    total = float(cover.sum())
    if total <= 0:
        return None
    rows, cols = np.nonzero(comp)
    wts = cover[rows, cols]
    u = float((wts * (cols + 0.5)).sum() / total)
    v = float((wts * (rows + 0.5)).sum() / total)
    return u, v, total


def observe_lights(
    work: WorkDir,
    capture: Capture,
    cam_from_rig: dict[str, tuple[np.ndarray, np.ndarray]],
    nominal_rig: np.ndarray,
    prior_sigma_m: float = 0.003,
    pixel_sigma: float = 0.25,
    margin_px: float = 2.0,
    intrinsics: dict[str, np.ndarray] | None = None,
) -> BulbEstimate:
    """Rig-frame light positions from the bulbs seen in the processed frames (see the module doc).

    `cam_from_rig`: camera id -> stage-rig-to-camera (R, t) in metres; `nominal_rig`: (L, 3) nominal positions.
    `intrinsics`: camera id -> raw-resolution K (default: stage.yaml's); distortion is ignored. Only frames
    where a light's nominal position projects inside a camera's image are read.
    """
    from lightstage.preprocess.processed import read_processed

    stage = capture.stage
    w, h = stage.width // DOWNSCALE, stage.height // DOWNSCALE
    positions = np.array(nominal_rig, dtype=np.float64, copy=True)
    est = BulbEstimate(positions)
    masks: dict[tuple[str, str], np.ndarray] = {}
    for li, light in enumerate(stage.lights):
        p0 = positions[li]
        rays = []
        for cam in stage.cameras:
            if cam.id not in cam_from_rig:
                continue
            R, t = cam_from_rig[cam.id]
            K = np.array(intrinsics.get(cam.id, cam.K) if intrinsics else cam.K, dtype=np.float64)
            K[:2] /= DOWNSCALE
            pc = R @ p0 + t
            if pc[2] <= 0:
                continue
            u, v = (K @ pc)[:2] / pc[2]
            if not (margin_px <= u <= w - margin_px and margin_px <= v <= h - margin_px):
                continue
            found = []
            for g in stage.group_names:
                path = work.frame(FrameId(g, cam.id, light.index))
                if not path.is_file():
                    continue
                try:
                    rgb, sat = read_processed(path, (w, h))
                except LightstageError:
                    continue
                est.frames_read += 1
                key = (g, cam.id)
                if key not in masks:
                    m = cv2.imread(str(work.mask(ViewId(g, cam.id))), cv2.IMREAD_GRAYSCALE)
                    masks[key] = m > 127 if m is not None else np.zeros((h, w), bool)
                hit = detect_bulb(rgb, sat, masks[key], stage.saturation)
                if hit is not None:
                    found.append(hit)
            if not found:
                continue
            # The whole disc has the largest area; keep the groups that show it so and take the median centre.
            areas = np.array([f[2] for f in found])
            keep = [f for f in found if f[2] >= 0.9 * areas.max()]
            u_m = float(np.median([f[0] for f in keep]))
            v_m = float(np.median([f[1] for f in keep]))
            if np.hypot(u_m - u, v_m - v) > 20.0:
                continue  # not this light's bulb (the nominal position is a few pixels off at most)
            centre = -R.T @ t
            d = R.T @ np.linalg.solve(K, np.array([u_m, v_m, 1.0]))
            d /= np.linalg.norm(d)
            depth = float(np.linalg.norm(p0 - centre))
            rays.append((cam.id, centre, d, depth * pixel_sigma / K[0, 0]))
        if not rays:
            continue
        A = np.eye(3) / prior_sigma_m**2
        b = p0 / prior_sigma_m**2
        for _, c, d, sigma in rays:
            P = np.eye(3) - np.outer(d, d)
            A += P / sigma**2
            b += P @ c / sigma**2
        positions[li] = np.linalg.solve(A, b)
        est.cameras_per_light[light.index] = [r[0] for r in rays]
        est.shift_mm[light.index] = float(1000.0 * np.linalg.norm(positions[li] - p0))
    return est
