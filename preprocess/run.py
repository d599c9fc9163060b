"""`run_preprocess`: raw OLAT frames -> processed frames, per-view statistics, masks, zones, flare rejects.

The stage driver; the tasks live in frame_task.py (chunks) and view_task.py (views), the previews and
the report in report.py. Work is split per view into chunks of lights. A chunk task decodes each raw frame once, writes its 4x
downscaled RGBS frame (atomically) and streams it into the chunk's partial statistics, which it saves
(atomically) as a partial file. A view task merges the partials in a tree, segments, scores flares and
writes the view's outputs; `view.json` is written last and marks the view finished. A final step picks one
exposure for the whole capture and writes the tonemapped previews (per view, as executor tasks), then
`reports/preprocess.json`.

Resuming: finished views are skipped; in unfinished views, chunks with a partial are skipped and frames
with a valid processed file are read back instead of decoded, so a killed run resumes with identical
outputs. Bad frames (missing, corrupt, wrong size, non-finite) are recorded and skipped.
"""

from __future__ import annotations

import time
from typing import Any

from lightstage.atomic import write_json_atomic
from lightstage.capture.layout import Capture, open_capture
from lightstage.dask_executor import in_dask_worker
from lightstage.errors import LightstageError, StageIncomplete
from lightstage.executor import Executor, LoopExecutor, TaskFailure
from lightstage.ids import FrameId, ViewId
from lightstage.preprocess.camera_task import CameraJob, camera_done, camera_key, finalise_camera
from lightstage.preprocess.config import PreprocessConfig
from lightstage.preprocess.flare import light_pixels
from lightstage.preprocess.frame_task import process_chunk
from lightstage.preprocess.jobs import (
    ChunkJob,
    ChunkRecord,
    ViewJob,
    ViewRecord,
    split_lights,
)
from lightstage.preprocess.report import add_group_flags, add_implausible, build_report, write_previews
from lightstage.preprocess.sfm_image import sfm_image_factor, spread_lights
from lightstage.preprocess.view_task import process_view, read_gt_mask, view_finished
from lightstage.records.ground_truth import GroundTruth
from lightstage.workdir import DOWNSCALE, WorkDir

# read_gt_mask: imported from here by the tests and benches
__all__ = ["PreprocessConfig", "run_preprocess", "process_chunk", "process_view", "read_gt_mask"]


# ---- orchestration --------------------------------------------------------------------------------------------
def run_preprocess(
    work: WorkDir, config: PreprocessConfig, executor: Executor | None = None, progress: bool = True
) -> dict[str, Any]:
    """Preprocess the capture named in WORK/capture.txt into WORK/preprocess; returns a summary dict."""
    t0 = time.perf_counter()
    if isinstance(config, dict):
        config = PreprocessConfig.from_dict(config)  # (a PreprocessConfig validates itself on creation)
    capture = open_capture(work.capture_path())
    stage = capture.stage
    if stage.width % DOWNSCALE or stage.height % DOWNSCALE:
        raise LightstageError(
            f"{capture.root / 'stage.yaml'}: resolution {stage.width}x{stage.height} is not a multiple of {DOWNSCALE}"
        )
    size = (stage.width // DOWNSCALE, stage.height // DOWNSCALE)
    lights = [lt.index for lt in stage.lights]
    intensities = {lt.index: tuple(float(x) for x in lt.intensity) for lt in stage.lights}
    sfm_factor = sfm_image_factor(stage.width, stage.height, config.sfm_max_side)
    sfm_lights = set(spread_lights(lights, config.sfm_lights)) if sfm_factor < DOWNSCALE else set()
    view_jobs: list[ViewJob] = []
    chunk_jobs: dict[ViewId, list[ChunkJob]] = {}
    for view in capture.views():
        in_view = light_pixels(
            stage.view_camera(view.group, view.camera),
            stage.light_positions_world(view.group),
            size,
            config.flare_margin,
        )
        raw = tuple(str(capture.frame_path(FrameId(view.group, view.camera, lt))) for lt in lights)
        gt = GroundTruth.of(capture.root).mask(view)
        user = capture.user_mask(view)
        chunks = split_lights(lights, config.chunk_lights)
        view_jobs.append(
            ViewJob(
                str(work.root),
                view.group,
                view.camera,
                tuple(lights),
                len(chunks),
                size,
                stage.saturation,
                config,
                str(gt) if gt.is_file() else None,
                raw,
                (stage.width, stage.height),
                capture.info.exposure_scale,
                str(user) if user.is_file() else None,
                tuple(in_view),
            )
        )
        chunk_jobs[view] = [
            ChunkJob(
                str(work.root),
                view.group,
                view.camera,
                i,
                c,
                raw[i * config.chunk_lights : i * config.chunk_lights + len(c)],
                (stage.width, stage.height),
                stage.saturation,
                capture.info.exposure_scale,
                config,
                tuple(intensities[lt] for lt in c),
                tuple(lt for lt in c if lt in sfm_lights),
                sfm_factor,
            )
            for i, c in enumerate(chunks)
        ]

    check_frames_exist(capture, view_jobs)
    records: dict[ViewId, ViewRecord] = {}
    todo: list[ViewJob] = []
    for job in view_jobs:
        done = view_finished(work, job)
        if done is not None:
            records[done.view] = done
        else:
            todo.append(job)
    finished_before = len(records)
    errors: list[str] = []
    chunk_results: list[ChunkRecord] = []
    t_frames = time.perf_counter()
    executor = executor or LoopExecutor()
    _run_views(executor, todo, chunk_jobs, records, chunk_results, errors, config, progress)
    t_views = time.perf_counter() - t_frames
    t_cams = time.perf_counter()
    _run_cameras(work, executor, view_jobs, records, errors, config, progress)
    t_cameras = time.perf_counter() - t_cams
    add_group_flags(work, records, config)
    t_prev = time.perf_counter()
    exposure = write_previews(
        work,
        [v for v in view_jobs if ViewId(v.group, v.camera) in records],
        records,
        config,
        executor,
        progress,
    )
    report = build_report(
        work, capture, config, view_jobs, records, chunk_results, errors, finished_before, exposure
    )
    add_implausible(report, capture, config, records)
    t_previews = time.perf_counter() - t_prev
    from lightstage.preprocess.probe import run_probe

    probe = run_probe(work, capture, executor, progress)
    if probe is not None:
        report["probe"] = probe
    report["timings"] = {
        "total_s": round(time.perf_counter() - t0, 3),
        "frames_and_views_s": round(t_views, 3),
        "cameras_s": round(t_cameras, 3),
        "previews_s": round(t_previews, 3),
        "probe_s": probe["seconds"] if probe is not None else None,
        "per_processed_frame_s": round(t_views / max(report["counts"]["processed"], 1), 4)
        if report["counts"]["processed"]
        else None,
    }
    write_json_atomic(work.report("preprocess"), report)
    summary = {k: report[k] for k in ("counts", "timings")}
    if "segmentation" in report:
        summary["segmentation"] = {k: v for k, v in report["segmentation"].items() if k != "iou"}
    if report["warnings"]:
        import sys

        shown = report["warnings"][:20]
        more = len(report["warnings"]) - len(shown)
        for line in shown:
            print(f"preprocess: warning: {line}", file=sys.stderr)
        if more:
            print(
                f"preprocess: warning: ... and {more} more (see {work.report('preprocess')})", file=sys.stderr
            )
        summary["warnings"] = len(report["warnings"])
    summary["rejected"] = len(report["rejected_frames"])
    summary["broken"] = len(report["broken_frames"])
    summary["flare_flagged"] = len(report["flare"]["flagged_frames"])
    summary["problems"] = len(report["problems"])
    summary["errors"] = len(errors)
    summary["report"] = str(work.report("preprocess"))
    summary["status"] = report["status"]
    if report["failure"]:  # the runner must not record the stage as done; a rerun retries what is missing
        missing = report["missing"]
        raise StageIncomplete(
            f"preprocess: {report['failure']}; see {work.report('preprocess')}",
            missing=missing["views"] + missing["frames"],
            summary=summary,
        )
    return summary


def check_frames_exist(capture: Capture, jobs: list[ViewJob]) -> None:
    """Refuse a capture none of whose expected frames exists (a path_template matching no file), naming the
    template and an expected path, before any work starts."""
    import os

    for job in jobs:
        if any(os.path.lexists(p) for p in job.raw_paths):
            return
    example = jobs[0].raw_paths[0] if jobs and jobs[0].raw_paths else "(no frames expected)"
    raise LightstageError(
        f"{capture.root / 'capture.yaml'}: path_template {capture.info.path_template!r} matches no frame "
        f"(e.g. {example} does not exist)"
    )


def _run_views(
    executor: Executor,
    todo: list[ViewJob],
    chunk_jobs: dict[ViewId, list[ChunkJob]],
    records: dict[ViewId, ViewRecord],
    chunk_results: list[ChunkRecord],
    errors: list[str],
    config: PreprocessConfig,
    progress: bool,
) -> None:
    """Every unfinished view through the executor: its chunks as tasks, then its view task on their records.
    Views are admitted in a bounded window (`config.window` tasks, default 4 per task slot) so partial files
    stay bounded; a view that still fails after the executor's retries is an error, and the batch goes on."""
    groups = [(job, chunk_jobs[ViewId(job.group, job.camera)]) for job in todo]
    done = executor.map_groups(
        _view_after_chunks,
        process_chunk,
        groups,
        desc="preprocess",
        unit="frame",
        weight=lambda job: len(job.lights),
        window=config.window or None,
        progress=progress,
        errors="return",
    )
    for job, rec in zip(todo, done, strict=True):
        view = ViewId(job.group, job.camera)
        if isinstance(rec, TaskFailure):
            errors.append(f"{view}: {rec.error}")
            continue
        records[view] = rec
        chunk_results.extend(ChunkRecord(**c) for c in rec.chunks)


def _run_cameras(
    work: WorkDir,
    executor: Executor,
    view_jobs: list[ViewJob],
    records: dict[ViewId, ViewRecord],
    errors: list[str],
    config: PreprocessConfig,
    progress: bool,
) -> None:
    """The camera step (camera_task.py) for every camera whose finished views changed since it last ran: the
    views' final masks. A failed camera is an error, and its views count as failed (the stage is incomplete; a
    rerun redoes the step from the views' own masks)."""
    by_camera: dict[str, list[ViewJob]] = {}
    for job in view_jobs:
        if ViewId(job.group, job.camera) in records:
            by_camera.setdefault(job.camera, []).append(job)
    todo = []
    for camera, jobs in by_camera.items():
        groups = [j.group for j in jobs]
        key = camera_key(camera, groups, config)
        cam = CameraJob(str(work.root), camera, tuple(groups), config, tuple(j.gt_mask for j in jobs), key)
        if not camera_done(work, cam):
            todo.append(cam)
    done = executor.map(
        finalise_camera,
        todo,
        desc="cameras",
        unit="camera",
        progress=progress and bool(todo),
        errors="return",
    )
    for cam, res in zip(todo, done, strict=True):
        if isinstance(res, TaskFailure):
            errors.append(f"camera {cam.camera} (views {', '.join(cam.groups)}): {res.error}")
            for group in cam.groups:
                records.pop(ViewId(group, cam.camera), None)
            continue
        for group, rec in res.items():
            records[ViewId(group, cam.camera)] = rec


def _view_after_chunks(job: ViewJob, chunk_records: list[ChunkRecord]) -> ViewRecord:
    """Executor task: runs once the view's chunk tasks are done (their records are the argument)."""
    if in_dask_worker():
        from lightstage.threads import set_library_threads

        set_library_threads(1)
    return process_view(job, list(chunk_records))
