"""The view task: merge a view's chunk partials, segment, score flares, build the SfM image and write the
view's outputs (view.json last); and the check that a view finished earlier is still current."""

from __future__ import annotations

import json
import os
import time
from collections.abc import Iterator
from dataclasses import asdict
from pathlib import Path

import numpy as np

from lightstage.atomic import write_json_atomic
from lightstage.errors import LightstageError
from lightstage.ids import FrameId, ViewId
from lightstage.preprocess.jobs import (
    PARTIALS,
    VIEW_RECORD,
    ChunkRecord,
    ViewJob,
    ViewRecord,
    camera_marker,
    file_signature,
    partial_path,
    remove_stale_temps,
    sfm_frame_path,
)
from lightstage.workdir import WorkDir


# ---- the view task --------------------------------------------------------------------------------------------
def process_view(job: ViewJob, chunk_records: list[ChunkRecord] | None = None) -> ViewRecord:
    """Merge a view's chunk partials (tree), segment, score flares, write the view's outputs; view.json
    last. `chunk_records` (from this run's chunk tasks) only feed the record's timings."""
    from lightstage.frames import write_exr, write_image
    from lightstage.preprocess.flare import view_flares, write_flare_masks
    from lightstage.preprocess.segment import iou, mask_flags, segment_masks, zone_map
    from lightstage.preprocess.sfm_image import upsample_mask
    from lightstage.preprocess.stats import ViewStats, empty_stats, merge_tree
    from lightstage.records.processed import to_half

    start = time.perf_counter()
    work = WorkDir.at(job.work_root)
    view = ViewId(job.group, job.camera)
    cfg = job.config
    key = cfg.stats_key()
    w, h = job.size
    thumbs: list[np.ndarray] = []
    sthumbs: list[np.ndarray] = []
    taus: list[np.ndarray] = []
    problems: dict[str, str] = {}
    paths = [partial_path(work, view, i, key) for i in range(job.chunks)]
    missing = [p for p in paths if not p.is_file()]
    if missing:
        raise LightstageError(f"{view}: chunk statistics missing ({missing[0]}); rerun to resume")

    def parts() -> Iterator[ViewStats]:
        for p in paths:
            s = ViewStats.load(p)
            thumbs.append(s.extras["thumbs"])
            sthumbs.append(s.extras["sthumbs"].astype(np.float32))
            taus.append(s.extras["taus"])
            for light, reason in json.loads(str(s.extras["records"]))["problems"]:
                problems[str(light)] = reason
            s.extras = {}
            yield s

    stats = merge_tree(parts(), consume=True) or empty_stats(h, w)  # parts loaded here: merged in place
    if stats.count == 0:
        stats = empty_stats(h, w)
    if stats.mean.shape[:2] != (h, w):
        raise LightstageError(
            f"{view}: statistics are {stats.mean.shape[1]}x{stats.mean.shape[0]}, expected {w}x{h}"
        )
    mask, inclusive, seg_info = segment_masks(stats, cfg, job.cutoff)
    user: dict = {}
    if job.user_mask:  # the capture's own mask is used as it is; ours is reported against it
        supplied = read_user_mask(job.user_mask, (w, h), view)
        user = {
            "path": job.user_mask,
            "signature": file_signature(job.user_mask),
            "iou_own": round(iou(mask, supplied), 5),
        }
        mask = inclusive = supplied
    zones = zone_map(mask, cfg.band_width)
    lum_thumbs = np.concatenate(thumbs) if thumbs else np.zeros((0, 1, 1), np.float32)
    sat_thumbs = np.concatenate(sthumbs) if sthumbs else np.zeros((0, 1, 1), np.float32)
    lights = list(stats.lights)
    pixels = dict(zip(job.lights, job.light_pixels, strict=True)) if job.light_pixels else {}
    flares = view_flares(lum_thumbs, sat_thumbs, mask, lights, pixels, cfg, job.cutoff)
    scores, rejected = flares.scores, flares.rejected
    level = foreground_level(stats.mean, mask, cfg.exposure_percentile)
    gt_iou = None
    if job.gt_mask and Path(job.gt_mask).is_file():
        gt_iou = iou(mask, read_gt_mask(job.gt_mask, (w, h)))
    sfm, sfm_lights = _sfm_image(work, job, set(lights) - set(rejected) - set(flares.regions))
    sfm_mask = upsample_mask(mask, (sfm.shape[1], sfm.shape[0])) > 0
    sfm_level = foreground_level(sfm, sfm_mask, cfg.exposure_percentile)

    vdir = work.view_dir(view)
    # the camera's cross-group step must run again on this view's new outputs (camera_task.py)
    camera_marker(work, job.camera).unlink(missing_ok=True)
    remove_stale_temps(vdir, ["stats", "mean", "sfm", "mask", "zones", "view"])
    stats.save(
        vdir / "stats.npz",
        extras={
            "mask": mask,
            "mask_inclusive": inclusive,
            "flare_scores": np.asarray(scores, np.float32),
            "lit_thresholds": np.concatenate(taus) if taus else np.zeros(0),
        },
    )
    write_exr(work.mean_image(view), to_half(stats.mean), compression="zip")
    write_exr(work.sfm_hdr(view), to_half(sfm), compression="zip")
    write_image(work.mask(view), (mask * 255).astype(np.uint8))
    write_image(work.zones(view), zones)
    flared = write_flare_masks(work, view, flares.regions, (w, h), cfg.flare_thumb)
    record = ViewRecord(
        group=job.group,
        camera=job.camera,
        key=cfg.view_key(),
        lights=lights,
        problems=problems,
        problem_files={
            lt: file_signature(p)
            for lt, p in zip(map(str, job.lights), job.raw_paths, strict=True)
            if lt in problems
        },
        flare_scores={str(lt): round(float(s), 5) for lt, s in zip(lights, scores, strict=True)},
        rejected=rejected,
        foreground_fraction=float(mask.mean()),
        exposure_level=level,
        sfm_lights=sfm_lights,
        sfm_level=sfm_level,
        iou=gt_iou,
        seconds=time.perf_counter() - start,
        chunks=[asdict(r) for r in chunk_records or []],
        flags=mask_flags(mask, cfg),
        segmentation=seg_info,
        user_mask=user,
        flared=flared,
        frame_levels={str(lt): x for lt, x in flares.levels.items()},
    )
    write_json_atomic(vdir / VIEW_RECORD, asdict(record))
    for p in paths:
        p.unlink(missing_ok=True)
    for lt in job.lights:  # the SfM frames the chunks left (only for SfM lights, below DOWNSCALE)
        sfm_frame_path(work, view, lt).unlink(missing_ok=True)
    try:
        (vdir / PARTIALS).rmdir()
    except OSError:
        pass
    return record


def foreground_level(rgb: np.ndarray, mask: np.ndarray, percentile: float) -> float:
    """The luminance percentile of an image's foreground (0 without one): what the capture's exposure maps to 1."""
    from lightstage.tonemap import luminance

    return float(np.percentile(luminance(rgb)[mask], percentile)) if mask.any() else 0.0


def _sfm_image(work: WorkDir, job: ViewJob, usable: set[int]) -> tuple[np.ndarray, list[int]]:
    """The view's SfM image (see preprocess/sfm_image.py) and the lights in it: the configured spread of the
    capture's lights, less this view's bad and rejected frames."""
    from lightstage.preprocess.sfm_image import SfmSource, sfm_image_factor, sfm_mean_image, spread_lights

    cfg = job.config
    W, H = job.raw_size
    factor = sfm_image_factor(W, H, cfg.sfm_max_side)
    chosen = [lt for lt in spread_lights(list(job.lights), cfg.sfm_lights) if lt in usable]
    if not chosen:  # all of the spread's frames are bad here: the usable ones instead (none: a black image)
        chosen = spread_lights(sorted(usable), cfg.sfm_lights)
    if not chosen:
        return np.zeros((H // factor, W // factor, 3), np.float32), []
    view = ViewId(job.group, job.camera)
    src = SfmSource(
        lights=chosen,
        raw_paths=dict(zip(job.lights, job.raw_paths, strict=True)),
        processed_paths={lt: str(work.frame(FrameId(job.group, job.camera, lt))) for lt in chosen},
        raw_size=(W, H),
        factor=factor,
        cutoff=job.cutoff,
        exposure_scale=job.exposure_scale,
        band_rows=cfg.band_rows,
        cached={lt: str(sfm_frame_path(work, view, lt)) for lt in chosen},
        decoder=cfg.decoder,
        read_timeout_s=cfg.read_timeout_s,
    )
    try:
        return sfm_mean_image(src, cfg.sfm_trim), chosen
    except LightstageError as e:
        raise LightstageError(f"{view}: SfM image: {e}") from None


def read_gt_mask(path: str | os.PathLike[str], size: tuple[int, int]) -> np.ndarray:
    """A full-resolution ground-truth mask PNG, area-downscaled to `size` (w, h): foreground where more than
    half of the source pixels are (strict majority)."""
    from lightstage.frames import read_image

    return downscale_mask(read_image(path)[..., 0], size)


def downscale_mask(img: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """A full-resolution mask image (one channel, 0-1 or 0-255) at `size` (w, h): foreground where more than half
    of the source pixels are (strict majority)."""
    import cv2

    m = img > 0.5 * (255.0 if img.max() > 1.0 else 1.0)
    return cv2.resize(m.astype(np.float32), size, interpolation=cv2.INTER_AREA) > 0.5


def read_user_mask(path: str | os.PathLike[str], size: tuple[int, int], view: ViewId) -> np.ndarray:
    """A capture's own mask of a view (masks/<g>/<c>.png, at the raw resolution) at the processed `size`, like a
    ground-truth mask; an unreadable or wrongly sized one is an error naming it."""
    from lightstage.frames import read_image
    from lightstage.workdir import DOWNSCALE

    try:
        img = read_image(path)
    except (OSError, ValueError) as e:
        raise LightstageError(
            f"{path}: cannot read the mask of view {view} ({e}); fix or remove it"
        ) from None
    w, h = size
    if (img.shape[1], img.shape[0]) != (w * DOWNSCALE, h * DOWNSCALE):
        raise LightstageError(
            f"{path}: mask of view {view} is {img.shape[1]}x{img.shape[0]}, expected the raw frames' "
            f"{w * DOWNSCALE}x{h * DOWNSCALE}; fix or remove it"
        )
    return downscale_mask(img[..., 0], size)


def view_finished(work: WorkDir, job: ViewJob) -> ViewRecord | None:
    """The view's record when its outputs are complete and current, else None."""
    from lightstage.records.processed import processed_ok

    path = work.view_dir(ViewId(job.group, job.camera)) / VIEW_RECORD
    if not path.is_file():
        return None
    try:
        d = json.loads(path.read_text())
        record = ViewRecord(**d)
    except (OSError, ValueError, TypeError):
        return None
    if record.key != job.config.view_key():
        return None
    v = ViewId(job.group, job.camera)
    for p in (
        work.mask(v),
        work.zones(v),
        work.mean_image(v),
        work.sfm_hdr(v),
        work.view_dir(v) / "stats.npz",
    ):
        if not p.is_file():
            return None
    for lt in record.flared:
        if not work.flare_mask(FrameId(job.group, job.camera, int(lt))).is_file():
            return None
    for lt in record.lights:
        if not processed_ok(work.frame(FrameId(job.group, job.camera, lt)), job.size):
            return None
    for lt, raw in zip(job.lights, job.raw_paths, strict=False):  # a bad frame whose raw file changed
        sig = record.problem_files.get(str(lt))
        if sig is not None and file_signature(raw) != sig:
            return None
    if set(record.lights) | {int(k) for k in record.problems} != set(job.lights):
        return None
    user = record.user_mask.get("signature") if record.user_mask else None
    now = file_signature(job.user_mask) if job.user_mask else None
    if (user is None) != (now is None) or (now is not None and list(now) != list(user)):
        return None  # a user mask appeared, went or changed
    return record
