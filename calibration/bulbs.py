"""Light positions from the bulbs visible in the frames: clipped discs of rig-locked lights, triangulated.

A light that a camera sees directly shows as a small clipped disc in that camera's frame of that light. Lights
and cameras are locked to the rig, so in the stage rig frame each such observation is a ray from the camera
centre towards the bulb, the same in every group (the groups only change what the object hides). Per (light,
camera) the disc centre is taken from the processed frames of the groups where the disc is whole (round, so
neither partly hidden nor cut by the image border; clear of the object mask, or confirmed by several groups):
a `BulbSighting` (`find_bulbs`). Sightings do not depend on the rig's gauge, so they are found once and turned
into rays for any rig estimate:
`bulb_rays` turns them into `light_rays.LightRay`s: a light seen by two or more cameras is triangulated, one
seen by a single camera constrains the 2 coordinates across its ray (`light_rays.locate_lights`,
`light_rays.gauge_points`).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from lightstage.calibration.light_rays import LightRay
from lightstage.cameras import pixel_rays, project, world_to_camera
from lightstage.capture.layout import Capture
from lightstage.capture.stage import Stage
from lightstage.errors import LightstageError
from lightstage.ids import FrameId, ViewId
from lightstage.tonemap import luminance
from lightstage.workdir import DOWNSCALE, WorkDir


@dataclass(frozen=True)
class BulbSighting:
    """A light's bulb seen directly by a camera: disc centre in processed pixels (median over groups)."""

    light: int  # light index (= row of the stage's nominal rig-frame positions)
    camera: str
    uv: tuple[float, float]
    groups: list[str]  # the groups whose frames showed the whole disc
    touching_mask: bool = False  # confirmed by agreeing groups, not by a clear gap to the object mask


@dataclass
class BulbSightings:
    """What `find_bulbs` saw, with counts for the report."""

    sightings: list[BulbSighting] = field(default_factory=list)
    candidates: int = 0  # (light, camera) pairs where the nominal light projects inside the image
    frames_read: int = 0
    unconfirmed: int = 0  # pairs with round discs, but touching the mask and agreeing in too few groups
    read_errors: list[str] = field(default_factory=list)


def processed_intrinsics(
    stage: Stage, intrinsics: dict[str, np.ndarray] | None = None
) -> dict[str, np.ndarray]:
    """Camera id -> processed-resolution K, from the raw-resolution `intrinsics` where given, else stage.yaml's."""
    out = {}
    for cam in stage.cameras:
        K = np.array(intrinsics.get(cam.id, cam.K) if intrinsics else cam.K, dtype=np.float64)
        K[:2] /= DOWNSCALE
        out[cam.id] = K
    return out


@dataclass(frozen=True)
class BulbDisc:
    """A clipped blob of one processed frame: coverage-weighted centre (pixel centres at i + 0.5), area
    (pixels), roundness (minor / major second moment) and whether it touches the dilated object mask."""

    u: float
    v: float
    area: float
    roundness: float
    touches_mask: bool


def detect_bulb(
    rgb: np.ndarray,
    saturated: np.ndarray,
    mask: np.ndarray,
    saturation: float,
    min_area: int = 2,
    near: tuple[float, float] | None = None,
    max_offset_px: float = 20.0,
    min_roundness: float = 0.95,
) -> BulbDisc | None:
    """The whole (round) clipped blob nearest `near` (within `max_offset_px`), or the largest one without `near`;
    None if there is none.

    The coverage of each processed pixel is recovered from its area-averaged value between the local background
    and the clip level, so the centre is sub-pixel. A bulb partly hidden behind the object or cut by the image
    border is a disc with a piece cut off, and its second moments are no longer isotropic: `min_roundness`
    rejects it (whole discs measure >= 0.97, one with 1% of its area hidden 0.93; a disc that merely reaches
    the last row or column is whole, so touching the border alone is no reason). Touching the (dilated) object
    `mask` is only flagged: a segmentation can swallow a bulb and its glow next to the object, so the caller
    decides.
    """
    mask = np.asarray(mask, bool)
    near_object = cv2.dilate(mask.astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
    if not saturated.any():
        return None
    n, labels, stats, _ = cv2.connectedComponentsWithStats(saturated.astype(np.uint8), connectivity=8)
    lum = luminance(rgb)
    top = float(saturation)
    best: tuple[float, BulbDisc] | None = None
    for i in range(1, n):
        area = stats[i, cv2.CC_STAT_AREA]
        if area < min_area:
            continue
        comp = labels == i
        ring = (cv2.dilate(comp.astype(np.uint8), np.ones((7, 7), np.uint8)) > 0) & ~saturated
        outside = ring & ~mask
        ring = outside if outside.sum() >= 8 else ring
        bg = float(np.median(lum[ring])) if ring.any() else 0.0
        if top <= bg:
            continue
        rows, cols = np.nonzero(comp)
        wts = np.clip((lum[rows, cols] - bg) / (top - bg), 0.0, 1.0)
        total = float(wts.sum())
        if total <= 0:
            continue
        xy = np.stack([cols + 0.5, rows + 0.5], axis=1)
        centre = (wts[:, None] * xy).sum(0) / total
        d = xy - centre
        cov = (wts[:, None, None] * d[:, :, None] * d[:, None, :]).sum(0) / total + np.eye(2) / 12.0
        ev = np.linalg.eigvalsh(cov)
        roundness = float(ev[0] / ev[1])
        if roundness < min_roundness:
            continue
        disc = BulbDisc(float(centre[0]), float(centre[1]), total, roundness, bool(near_object[comp].any()))
        if near is not None:
            dist = float(np.hypot(disc.u - near[0], disc.v - near[1]))
            if dist > max_offset_px:
                continue
            score = dist
        else:
            score = -total
        if best is None or score < best[0]:
            best = (score, disc)
    return best[1] if best is not None else None


def combine_discs(
    light: int,
    camera: str,
    discs: dict[str, BulbDisc],
    min_groups_touching: int = 3,
    area_tol: float = 0.03,
    centre_tol_px: float = 0.1,
) -> BulbSighting | None:
    """One sighting from the round discs of the groups' frames of a (light, camera), or None.

    The bulb is rig-locked, so its disc is the same in every group where nothing hides it, while the object
    turns: the whole disc has the largest area, and the groups within `area_tol` of it are kept. If any of them
    keeps clear of the object mask, those give the centre (median); otherwise (the segmentation took the bulb
    or its glow as foreground) at least `min_groups_touching` groups, i.e. different silhouettes, must agree:
    same area and centres within `centre_tol_px` of their median (a clipped highlight on the object moves
    with it from group to group).
    """
    if not discs:
        return None
    top = max(d.area for d in discs.values())
    keep = {g: d for g, d in discs.items() if d.area >= (1.0 - area_tol) * top}
    clear = {g: d for g, d in keep.items() if not d.touches_mask}
    if not clear and keep:
        u0 = float(np.median([d.u for d in keep.values()]))
        v0 = float(np.median([d.v for d in keep.values()]))
        keep = {g: d for g, d in keep.items() if np.hypot(d.u - u0, d.v - v0) <= centre_tol_px}
    use = clear or (keep if len(keep) >= min_groups_touching else {})
    if not use:
        return None
    u = float(np.median([d.u for d in use.values()]))
    v = float(np.median([d.v for d in use.values()]))
    return BulbSighting(light, camera, (u, v), sorted(use), touching_mask=not clear)


def find_bulbs(
    work: WorkDir,
    capture: Capture,
    cam_from_rig: dict[str, tuple[np.ndarray, np.ndarray]],
    nominal_rig: np.ndarray,
    intrinsics: dict[str, np.ndarray] | None = None,
    margin_px: float = 2.0,
    max_offset_px: float = 20.0,
    min_groups_touching: int = 3,
) -> BulbSightings:
    """Every (light, camera) whose bulb shows as a whole clipped disc in the processed frames (see the module doc).

    `cam_from_rig`: camera id -> stage-rig-to-camera (R, t) in metres (only used to find where to look);
    `nominal_rig`: (L, 3) nominal positions, in the order of `capture.stage.lights`; `intrinsics`: camera id ->
    raw-resolution K (default: stage.yaml's). Only frames where a light's nominal position projects inside a
    camera's image are read; a disc farther than `max_offset_px` (processed pixels) from there is not the bulb.
    See `combine_discs` for how the groups' discs make one sighting.
    """
    from lightstage.records.processed import read_mask, read_processed

    stage = capture.stage
    w, h = stage.width // DOWNSCALE, stage.height // DOWNSCALE
    out = BulbSightings()
    K_proc = processed_intrinsics(stage, intrinsics)
    for cam in stage.cameras:
        if cam.id not in cam_from_rig:
            continue
        R, t = cam_from_rig[cam.id]
        K = K_proc[cam.id]
        masks: dict[str, np.ndarray] = {}  # this camera's masks per group (read once, kept for one camera)
        for li, light in enumerate(stage.lights):
            p = np.asarray(nominal_rig[li], np.float64)
            if world_to_camera(p, R, t)[2] <= 0:  # behind the camera
                continue
            u, v = project(p, K, R, t)
            if not (margin_px <= u <= w - margin_px and margin_px <= v <= h - margin_px):
                continue
            out.candidates += 1
            found: dict[str, BulbDisc] = {}
            for g in stage.group_names:
                path = work.frame(FrameId(g, cam.id, light.index))
                if not path.is_file():
                    continue
                try:
                    rgb, sat = read_processed(path, (w, h))
                except LightstageError as e:
                    out.read_errors.append(str(e))
                    continue
                out.frames_read += 1
                if g not in masks:
                    mask_path = work.mask(ViewId(g, cam.id))
                    masks[g] = read_mask(mask_path) if mask_path.is_file() else np.zeros((h, w), bool)
                disc = detect_bulb(
                    rgb, sat, masks[g], stage.saturation, near=(u, v), max_offset_px=max_offset_px
                )
                if disc is not None:
                    found[g] = disc
            sighting = combine_discs(li, cam.id, found, min_groups_touching)
            if sighting is None:
                out.unconfirmed += bool(found)
                continue
            out.sightings.append(sighting)
    return out


def bulb_rays(
    sightings: list[BulbSighting],
    cam_from_rig: dict[str, tuple[np.ndarray, np.ndarray]],
    K_proc: dict[str, np.ndarray],
    pixel_sigma: float = 0.1,
) -> list[LightRay]:
    """Each sighting as a ray from its camera centre through the disc centre (rig frame of `cam_from_rig`,
    metres; `K_proc`: processed-resolution K per camera); angular std `pixel_sigma` / fx."""
    rays = []
    for s in sightings:
        if s.camera not in cam_from_rig:
            continue
        R, t = (np.asarray(x, np.float64) for x in cam_from_rig[s.camera])
        K = np.asarray(K_proc[s.camera], np.float64)
        centre, d = pixel_rays(np.asarray(s.uv, np.float64), K, R, t)
        rays.append(LightRay(s.light, centre, d, pixel_sigma / K[0, 0], f"bulb {s.camera}"))
    return rays
