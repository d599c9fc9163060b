"""After the views: group flags, the tonemapped previews with one exposure per capture, and the stage report."""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from lightstage.atomic import write_json_atomic
from lightstage.capture.layout import Capture
from lightstage.executor import Executor, LoopExecutor
from lightstage.ids import FrameId, ViewId
from lightstage.preprocess.config import PreprocessConfig
from lightstage.preprocess.jobs import (
    PREVIEWS,
    VIEW_RECORD,
    ChunkRecord,
    ViewJob,
    ViewRecord,
    remove_stale_temps,
)
from lightstage.workdir import DOWNSCALE, WorkDir


def add_group_flags(work: WorkDir, records: dict[ViewId, ViewRecord], config: PreprocessConfig) -> None:
    """Flag views whose foreground fraction disagrees strongly with the other views of their group (rewrites
    their view.json; the flag is dropped again when a rerun finds them consistent)."""
    from lightstage.preprocess.segment import group_flags

    by_group: dict[str, dict[str, float]] = {}
    for v, rec in records.items():
        by_group.setdefault(v.group, {})[v.camera] = rec.foreground_fraction
    for group, fractions in by_group.items():
        odd = group_flags(fractions, config.flag_group_ratio)
        for camera in fractions:
            rec = records[ViewId(group, camera)]
            own = [f for f in rec.flags if not f.startswith("foreground fraction ")]
            flags = own + ([odd[camera]] if camera in odd else [])
            if flags != rec.flags:
                rec.flags = flags
                write_json_atomic(work.view_dir(rec.view) / VIEW_RECORD, asdict(rec))


def implausible_views(
    records: dict[ViewId, ViewRecord], config: PreprocessConfig
) -> list[tuple[ViewId, list[str]]]:
    """The views whose final mask fails the plausibility checks (its `flags`: empty, flooding the frame,
    touching most of the border, far off its group's other views) and that neither have the capture's own mask
    nor are listed in `accept_masks`: (view, reasons), in view order."""
    accepted = set(config.accept_masks)
    return [
        (v, rec.flags)
        for v, rec in sorted(records.items(), key=lambda kv: (kv[0].group, kv[0].camera))
        if rec.flags and not rec.user_mask and str(v) not in accepted
    ]


def add_implausible(
    report: dict[str, Any], capture: Capture, config: PreprocessConfig, records: dict[ViewId, ViewRecord]
) -> None:
    """Make implausible masks an error of the stage: the report lists them (`implausible_masks`), its status is
    incomplete, and `failure` names the first view, its reasons and the two ways to fix it."""
    bad = implausible_views(records, config)
    report["implausible_masks"] = [{"view": str(v), "reasons": r} for v, r in bad]
    if not bad:
        return
    v, reasons = bad[0]
    more = f" (and {len(bad) - 1} more views)" if len(bad) > 1 else ""
    why = (
        f"view {v}: implausible mask ({'; '.join(reasons)}){more}; supply its mask as "
        f'{capture.user_mask(v)}, or accept it in the preprocess config: accept_masks: ["{v}"]'
    )
    report["status"] = "incomplete"
    report["failure"] = "; ".join(x for x in (report.get("failure"), why) if x)
    missing = report["missing"]["views"]
    missing.extend(str(w) for w, _ in bad if str(w) not in missing)


# ---- previews and report ----------------------------------------------------------------------------------------
@dataclass(frozen=True)
class PreviewJob:
    """One view's previews with the capture's exposures (picklable: previews run as executor tasks)."""

    work_root: str
    group: str
    camera: str
    exposure: float
    sfm_exposure: float
    band_width: int
    flags: tuple[str, ...]


def preview_paths(work: WorkDir, view: ViewId) -> tuple[Path, Path, Path, Path]:
    """wellit.png, overlay.png, sfm.png and sfm_mask.png of a view."""
    return (work.wellit(view), work.view_dir(view) / "overlay.png", work.sfm_image(view), work.sfm_mask(view))


def write_previews(
    work: WorkDir,
    jobs: list[ViewJob],
    records: dict[ViewId, ViewRecord],
    config: PreprocessConfig,
    executor: Executor | None = None,
    progress: bool = False,
) -> float:
    """Write wellit.png (8-bit tonemapped mean image), overlay.png, and the SfM image (sfm.png) with its mask
    (sfm_mask.png) for every finished view, with one exposure for the whole capture per kind of image (and
    WORK/preprocess/sfm_images.json); views whose previews already use those exposures are skipped. The views
    run as executor tasks (`write_view_previews`); the book of what was written is kept here."""

    def auto(levels: list[float]) -> float:
        levels = [x for x in levels if x > 0]
        return float(np.float32(config.exposure or (1.0 / float(np.median(levels)) if levels else 1.0)))

    exposure = auto([r.exposure_level for r in records.values()])
    sfm_exposure = auto([r.sfm_level for r in records.values()])
    book_path = work.preprocess_dir / PREVIEWS
    remove_stale_temps(work.preprocess_dir, [Path(PREVIEWS).stem, work.sfm_info.stem])
    remove_stale_temps(work.report("preprocess").parent, ["preprocess"])
    try:
        book = json.loads(book_path.read_text()) if book_path.is_file() else {}
    except (OSError, ValueError):
        book = {}
    todo: list[tuple[PreviewJob, dict[str, Any]]] = []
    for job in jobs:
        view = ViewId(job.group, job.camera)
        rec = records[view]
        stamp = {
            "exposure": exposure,
            "sfm_exposure": sfm_exposure,
            "view_key": rec.key,
            "lights": len(rec.lights),
            "flags": rec.flags,
            "foreground_fraction": rec.foreground_fraction,  # the mask (the camera step may change it)
        }
        outputs = preview_paths(work, view)
        remove_stale_temps(work.view_dir(view), [p.stem for p in outputs])
        if book.get(str(view)) == stamp and all(p.is_file() for p in outputs):
            continue
        preview = PreviewJob(
            str(work.root),
            view.group,
            view.camera,
            exposure,
            sfm_exposure,
            config.band_width,
            tuple(rec.flags),
        )
        todo.append((preview, stamp))
    executor = executor or LoopExecutor()
    executor.map(
        write_view_previews,
        [t for t, _ in todo],
        desc="previews",
        unit="view",
        progress=progress and bool(todo),
    )
    for preview, stamp in todo:
        book[str(ViewId(preview.group, preview.camera))] = stamp
    if todo:
        write_json_atomic(book_path, book)
    if jobs:
        from lightstage.preprocess.sfm_image import sfm_image_factor, spread_lights

        W, H = jobs[0].raw_size
        f = sfm_image_factor(W, H, config.sfm_max_side)
        # the lights each view's image is built from, before its own bad and rejected frames are left out
        lights = len(spread_lights(list(jobs[0].lights), config.sfm_lights))
        info = {"factor": f, "size": [W // f, H // f], "lights": lights, "exposure": sfm_exposure}
        write_json_atomic(work.sfm_info, info)
    return exposure


def write_view_previews(job: PreviewJob) -> None:
    """Executor task: a view's four preview PNGs from its mean image, mask and SfM image (`write_png`)."""
    from lightstage.dask_executor import in_dask_worker
    from lightstage.frames import read_exr, write_png
    from lightstage.preprocess.segment import overlay, zone_map
    from lightstage.preprocess.sfm_image import upsample_mask
    from lightstage.records.processed import read_mask, to_float
    from lightstage.tonemap import tonemap_u8

    if in_dask_worker():
        from lightstage.threads import set_library_threads

        set_library_threads(1)
    work, view = WorkDir.at(job.work_root), ViewId(job.group, job.camera)
    outputs = preview_paths(work, view)

    def linear(path: Path) -> np.ndarray:
        x = read_exr(path)
        return to_float(x) if x.dtype == np.float16 else x.astype(np.float32)

    img = tonemap_u8(linear(work.mean_image(view)), job.exposure)
    mask = read_mask(work.mask(view))
    write_png(outputs[0], img)
    write_png(outputs[1], overlay(img, mask, zone_map(mask, job.band_width), list(job.flags)))
    sfm = linear(work.sfm_hdr(view))
    write_png(outputs[2], tonemap_u8(sfm, job.sfm_exposure))
    write_png(outputs[3], upsample_mask(mask, (sfm.shape[1], sfm.shape[0])))


def build_report(
    work: WorkDir,
    capture: Capture,
    config: PreprocessConfig,
    jobs: list[ViewJob],
    records: dict[ViewId, ViewRecord],
    chunk_results: list[ChunkRecord],
    errors: list[str],
    finished_before: int,
    exposure: float,
) -> dict[str, Any]:
    """The stage report: counts, problems, flare scores and flagged frames, broken frames, rejects (broken
    frames, and flare frames under flare_policy drop: the split leaves them out), flagged views, segmentation IoU."""
    from lightstage.preprocess.broken import broken_frames

    n_lights = len(capture.stage.lights)
    problems, rejected, flagged, scores, ious = [], [], [], {}, {}
    masks_flagged: list[dict[str, Any]] = []
    flare_flagged: list[dict[str, Any]] = []
    levels = {v: {int(lt): x for lt, x in r.frame_levels.items()} for v, r in records.items()}
    broken = broken_frames(levels, config.broken_sigmas, config.broken_min_stops)
    broken_per_view: dict[ViewId, int] = {}
    for frame in broken:
        view = ViewId(frame.group, frame.camera)
        broken_per_view[view] = broken_per_view.get(view, 0) + 1
    for job in jobs:
        view = ViewId(job.group, job.camera)
        rec = records.get(view)
        if rec is None:
            continue
        for lt, reason in sorted(rec.problems.items(), key=lambda kv: int(kv[0])):
            problems.append({"frame": str(FrameId(view.group, view.camera, int(lt))), "reason": reason})
        rejected.extend(str(FrameId(view.group, view.camera, lt)) for lt in rec.rejected)
        scores[str(view)] = rec.flare_scores
        flare_flagged.extend(
            {"frame": str(FrameId(view.group, view.camera, int(lt))), "fraction": f}
            for lt, f in sorted(rec.flared.items(), key=lambda kv: int(kv[0]))
        )
        lost = len(rec.problems) + len(rec.rejected) + broken_per_view.get(view, 0)
        if n_lights and lost / n_lights > config.max_lost_fraction:
            flagged.append(
                {
                    "view": str(view),
                    "lost": lost,
                    "bad": len(rec.problems),
                    "rejected": len(rec.rejected),
                    "broken": broken_per_view.get(view, 0),
                    "fraction": round(lost / n_lights, 4),
                }
            )
        if rec.flags:
            masks_flagged.append(
                {
                    "view": str(view),
                    "foreground_fraction": round(rec.foreground_fraction, 4),
                    "reasons": rec.flags,
                }
            )
        if rec.iou is not None:
            ious[str(view)] = round(rec.iou, 5)
    counts = {
        "views": len(jobs),
        "views_finished": len(records),
        "views_finished_before": finished_before,
        "views_failed": len(jobs) - len(records),
        "frames": len(jobs) * n_lights,
        "processed": sum(c.processed for c in chunk_results),
        "reused": sum(c.reused for c in chunk_results),
        "chunks_resumed": sum(1 for c in chunk_results if c.resumed),
        "frames_ok": sum(len(r.lights) for r in records.values()),
        "bad": len(problems),
        "rejected": len(rejected) + len(broken),
        "broken": len(broken),
        "flare_flagged": len(flare_flagged),
        "flagged_views": len(flagged),
        "flagged_masks": len(masks_flagged),
    }
    report: dict[str, Any] = {
        "stage": "preprocess",
        "capture": str(capture.root),
        "config": config.to_dict(),
        "config_key": config.view_key(),
        "processed_size": list(jobs[0].size) if jobs else None,
        "downscale": DOWNSCALE,
        # the path that decoded most frames, and frames per decoder (identical outputs: decoder_choice.py)
        "decoder": decoder_ran(config.decoder, chunk_results),
        "decoders": decoder_summary(config.decoder, chunk_results),
        "exposure": exposure,
        "counts": counts,
        "problems": problems,
        "rejected_frames": rejected + [str(f) for f in broken],
        "broken_frames": [{"frame": str(f), "reason": why} for f, why in broken.items()],
        "flagged_views": flagged,
        "flagged_masks": masks_flagged,
        "flare": {
            "policy": config.flare_policy,
            "threshold": config.flare_threshold,
            "scores": scores,
            "flagged_frames": flare_flagged,
        },
        "warnings": [f"view {f['view']} lost {f['lost']} of {n_lights} frames" for f in flagged]
        + [f"frame {f} dropped: {why}" for f, why in list(broken.items())[:20]]
        + [f"view {f['view']}: suspicious mask: {'; '.join(f['reasons'])}" for f in masks_flagged],
        "errors": errors,
    }
    report.update(outcome(jobs, records, problems, errors, counts["frames"], config.max_bad_fraction))
    if ious:
        vals = np.array(list(ious.values()))
        worst = min(ious, key=ious.get)
        report["segmentation"] = {
            "ground_truth": True,
            "iou_mean": round(float(vals.mean()), 5),
            "iou_worst": round(float(vals.min()), 5),
            "worst_view": worst,
            "iou": ious,
        }
    return report


def outcome(
    jobs: list[ViewJob],
    records: dict[ViewId, ViewRecord],
    problems: list[dict[str, str]],
    errors: list[str],
    frames: int,
    max_bad_fraction: float,
) -> dict[str, Any]:
    """The report's `status` ("complete" or "incomplete"), `missing` (the views that failed and the frames that
    are missing or bad) and `failure` (why the stage must not count as done, or None). Incomplete: any view
    failed (its outputs do not exist), or more than `max_bad_fraction` of the capture's frames are missing/bad."""
    failed = [str(ViewId(j.group, j.camera)) for j in jobs if ViewId(j.group, j.camera) not in records]
    bad = [p["frame"] for p in problems]
    fraction = len(bad) / frames if frames else 0.0
    why = []
    if failed:
        first = errors[0] if errors else failed[0]
        why.append(f"{len(failed)} of {len(jobs)} views failed (first: {first})")
    if fraction > max_bad_fraction:
        why.append(
            f"{len(bad)} of {frames} frames are missing or bad, more than max_bad_fraction = {max_bad_fraction:g}"
        )
    return {
        "status": "incomplete" if why else "complete",
        "missing": {
            "views": failed,
            "frames": bad,
            "bad_fraction": round(fraction, 6),
            "limit": max_bad_fraction,
        },
        "failure": "; ".join(why) or None,
    }


def decoder_summary(configured: str, chunks: list[ChunkRecord]) -> dict[str, Any]:
    """Which decoders ran (frames per decoder, this run's chunks) and, under `auto`, what each worker process
    measured before choosing (median probe CPU-s per frame, one entry per distinct measurement)."""
    frames: dict[str, int] = {}
    probes: list[dict[str, float]] = []
    for c in chunks:
        for d, n in c.decoded.items():
            frames[d] = frames.get(d, 0) + n
        if c.decoder_probe and c.decoder_probe not in probes:
            probes.append(c.decoder_probe)
    return {"configured": configured, "frames": frames, "probe_cpu_s": probes}


def decoder_ran(configured: str, chunks: list[ChunkRecord]) -> str:
    """The decoder that decoded most of this run's frames (the configured one when none was decoded)."""
    frames = decoder_summary(configured, chunks)["frames"]
    return max(frames, key=frames.get) if frames else configured
