"""The camera task: once every view of a camera has its own mask, the cross-group consistency step
(consistency.py) gives each view its final mask; mask.png, zones.png and view.json are rewritten, and a marker
(preprocess/cameras/<camera>.json, written last) records what it was computed from, so a rerun skips it or
redoes it from the views' own masks (kept in stats.npz as `mask`): resumable, with identical results."""

from __future__ import annotations

import hashlib
import json
import os
from collections import Counter
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from lightstage.atomic import write_json_atomic
from lightstage.errors import LightstageError
from lightstage.ids import ViewId
from lightstage.npyio import load_npz
from lightstage.preprocess.config import PreprocessConfig
from lightstage.preprocess.jobs import VIEW_RECORD, ViewRecord, camera_marker
from lightstage.workdir import WorkDir

CAMERA_FORMAT = 2  # bumped when the step changes meaning (2: structure_parts decides what leaves)


@dataclass(frozen=True)
class CameraJob:
    """The finished views of one camera (groups in order) and what the step needs."""

    work_root: str
    camera: str
    groups: tuple[str, ...]
    config: PreprocessConfig
    gt_masks: tuple[str | None, ...]
    key: str


def camera_key(camera: str, groups: list[str], config: PreprocessConfig) -> str:
    """Hash of the step's settings, the view key and the camera's views. A view task that rewrites a view's outputs
    removes its camera's marker first (view_task.process_view), so a redone view makes the step run again."""
    keys = ("consistency", "consistency_max_removed", "background_sigmas", "band_width", "fill_holes")
    keys += ("min_component_fraction", "centre_weight", "open_radius", "flag_border_fraction")
    keys += ("flag_min_fraction", "flag_max_fraction", "exposure_percentile")
    blob = {
        "format": CAMERA_FORMAT,
        "view_key": config.view_key(),
        "camera": camera,
        "groups": sorted(groups),
    }
    blob.update({k: getattr(config, k) for k in keys})
    return hashlib.sha256(json.dumps(blob, sort_keys=True).encode()).hexdigest()[:16]


def camera_done(work: WorkDir, job: CameraJob) -> bool:
    """The marker is current: the step ran on exactly these views and settings."""
    try:
        return json.loads(camera_marker(work, job.camera).read_text()).get("key") == job.key
    except (OSError, ValueError):
        return False


def finalise_camera(job: CameraJob) -> dict[str, ViewRecord]:
    """Run the consistency step on a camera's views and write their final masks; group -> updated record."""
    from lightstage.frames import write_image
    from lightstage.preprocess.consistency import consistent_masks
    from lightstage.preprocess.segment import iou, mask_flags, zone_map
    from lightstage.preprocess.view_task import foreground_level, read_gt_mask

    work = WorkDir.at(job.work_root)
    cfg = job.config
    records: dict[str, ViewRecord] = {}
    means, masks, inclusive = {}, {}, {}
    for g in job.groups:
        vdir = work.view_dir(ViewId(g, job.camera))
        try:
            records[g] = ViewRecord(**json.loads((vdir / VIEW_RECORD).read_text()))
            d = load_npz(vdir / "stats.npz")
            means[g], masks[g] = d["mean"].astype(np.float32), d["mask"].astype(bool)
            inclusive[g] = d["mask_inclusive"].astype(bool) if "mask_inclusive" in d else masks[g]
        except (OSError, ValueError, TypeError, KeyError) as e:
            raise LightstageError(f"{vdir}: cannot read the view's outputs ({e}); rerun to redo it") from None
    # only views of the same frames are comparable (a bad frame in one group changes its mean)
    common, _ = Counter(tuple(records[g].lights) for g in job.groups).most_common(1)[0]
    same = [g for g in job.groups if tuple(records[g].lights) == common]
    final = {g: masks[g] for g in job.groups}
    info: dict[str, Any] = {"skipped": "off (config consistency: false)"}
    if cfg.consistency:
        stack, info = consistent_masks(
            np.stack([means[g] for g in same]),
            np.stack([inclusive[g] for g in same]),
            cfg,
            own=np.stack([masks[g] for g in same]),
        )
        final.update(zip(same, stack, strict=True))
        final.update({g: masks[g] for g in same if records[g].user_mask})  # the capture's own: as it is
        removed = info.pop("removed", [0] * len(same))
        per_view = dict(zip(same, removed, strict=True))
    else:
        per_view = {}
    for g, gt in zip(job.groups, job.gt_masks, strict=True):
        view = ViewId(g, job.camera)
        rec, mask = records[g], final[g]
        h, w = mask.shape
        n = per_view.get(g, 0)
        cons: dict[str, Any] = {**info, "removed": max(n, 0)}
        if g not in same:
            cons["skipped"] = "other frames than the camera's other groups"
        if n < 0:
            cons["skipped"] = f"{-n} fixed pixels are more than {cfg.consistency_max_removed:.0%} of the mask"
        if rec.user_mask:
            cons = {"skipped": "the capture's own mask, used as it is", "removed": 0}
        if gt and Path(gt).is_file():
            truth = read_gt_mask(gt, (w, h))
            cons["iou_view"] = round(iou(masks[g], truth), 5)
            rec.iou = iou(mask, truth)
        rec.consistency = cons
        rec.foreground_fraction = float(mask.mean())
        group_flags = [f for f in rec.flags if f.startswith("foreground fraction ")]
        rec.flags = mask_flags(mask, cfg) + group_flags
        rec.exposure_level = foreground_level(means[g], mask, cfg.exposure_percentile)
        rec.sfm_level = _sfm_level(work, view, mask, cfg.exposure_percentile)
        vdir = work.view_dir(view)
        write_image(work.mask(view), (mask * 255).astype(np.uint8))
        write_image(work.zones(view), zone_map(mask, cfg.band_width))
        write_json_atomic(vdir / VIEW_RECORD, asdict(rec))
    write_json_atomic(camera_marker(work, job.camera), {"key": job.key, "groups": list(job.groups)})
    return records


def _sfm_level(work: WorkDir, view: ViewId, mask: np.ndarray, percentile: float) -> float:
    """The SfM image's exposure level under the final mask (upsampled like sfm_mask.png)."""
    from lightstage.frames import read_exr
    from lightstage.preprocess.sfm_image import upsample_mask
    from lightstage.preprocess.view_task import foreground_level

    path = work.sfm_hdr(view)
    if not os.path.isfile(path):
        return 0.0
    sfm = read_exr(path).astype(np.float32)
    return foreground_level(sfm, upsample_mask(mask, (sfm.shape[1], sfm.shape[0])) > 0, percentile)
