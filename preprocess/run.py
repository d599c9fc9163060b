"""`run_preprocess`: raw OLAT frames -> processed frames, per-view statistics, masks, zones, flare rejects.

Work is split per view into chunks of lights. A chunk task decodes each raw frame once, writes its 4x
downscaled RGBS frame (atomically) and streams it into the chunk's partial statistics, which it saves
(atomically) as a partial file. A view task merges the partials in a tree, segments, scores flares and
writes the view's outputs; `view.json` is written last and marks the view finished. A final in-process step
writes the tonemapped previews with one exposure for the whole capture, then `reports/preprocess.json`.

Resuming: finished views are skipped; in unfinished views, chunks with a partial are skipped and frames
with a valid processed file are read back instead of decoded, so a killed run resumes with identical
outputs. Bad frames (missing, corrupt, wrong size, non-finite) are recorded and skipped.
"""

from __future__ import annotations

import json
import os
import time
from collections.abc import Iterator
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from lightstage.atomic import write_json_atomic
from lightstage.capture.layout import Capture, open_capture
from lightstage.errors import LightstageError
from lightstage.ids import FrameId, ViewId
from lightstage.preprocess.config import PreprocessConfig
from lightstage.records.ground_truth import GroundTruth
from lightstage.workdir import DOWNSCALE, WorkDir

__all__ = ["PreprocessConfig", "run_preprocess", "process_chunk", "process_view"]

VIEW_RECORD = "view.json"
PARTIALS = "partials"
PREVIEWS = "previews.json"


# ---- jobs and records (small, picklable) -----------------------------------------------------------------
@dataclass(frozen=True)
class ChunkJob:
    """One chunk: a few lights of one view, with everything a worker needs."""

    work_root: str
    group: str
    camera: str
    index: int
    lights: tuple[int, ...]
    raw_paths: tuple[str, ...]
    raw_size: tuple[int, int]  # (width, height)
    cutoff: float
    exposure_scale: float
    config: PreprocessConfig
    # per light of the chunk, its relative RGB intensity (stage.yaml); processed frames are divided by it
    intensities: tuple[tuple[float, float, float], ...] = ()


@dataclass(frozen=True)
class ChunkRecord:
    """What a chunk task reports: counts, per-frame problems, timings."""

    group: str
    camera: str
    index: int
    processed: int = 0
    reused: int = 0
    problems: tuple[tuple[int, str], ...] = ()
    seconds: float = 0.0
    cpu_seconds: float = 0.0  # CPU time of the task's process (all its threads) while it ran
    resumed: bool = False  # the partial statistics already existed


@dataclass(frozen=True)
class ViewJob:
    """One view's merge/segment/score step."""

    work_root: str
    group: str
    camera: str
    lights: tuple[int, ...]
    chunks: int
    size: tuple[int, int]  # processed (width, height)
    cutoff: float
    config: PreprocessConfig
    gt_mask: str | None = None
    raw_paths: tuple[str, ...] = ()
    raw_size: tuple[int, int] = (0, 0)  # (width, height)
    exposure_scale: float = 1.0


@dataclass
class ViewRecord:
    """A finished view (also stored as view.json): frames used, problems, flare scores, rejects, IoU."""

    group: str
    camera: str
    key: str
    lights: list[int]  # lights with a valid processed frame (in the statistics)
    problems: dict[str, str]  # light -> reason (frames that could not be processed)
    problem_files: dict[str, list[float]]  # light -> [size, mtime] of the raw file when it failed
    flare_scores: dict[str, float]  # light -> score
    rejected: list[int]
    foreground_fraction: float
    exposure_level: float  # high percentile of the mean image's foreground luminance
    sfm_lights: list[int] = field(default_factory=list)  # frames in the SfM image
    sfm_level: float = 0.0  # the same percentile of the SfM image's foreground luminance
    iou: float | None = None
    seconds: float = 0.0
    chunks: list[dict[str, Any]] = field(default_factory=list)
    # why the mask looks wrong (segment.mask_flags; group_flags added once every view is done); empty: fine
    flags: list[str] = field(default_factory=list)
    segmentation: dict[str, Any] = field(default_factory=dict)  # measured levels (segment.segment_view)

    @property
    def view(self) -> ViewId:
        return ViewId(self.group, self.camera)


# ---- helpers ------------------------------------------------------------------------------------------------
def _partial_path(work: WorkDir, view: ViewId, index: int, key: str) -> Path:
    return work.view_dir(view) / PARTIALS / f"chunk{index:04d}-{key}.npz"


def _chunks(lights: list[int], size: int) -> list[tuple[int, ...]]:
    return [tuple(lights[i : i + size]) for i in range(0, len(lights), size)]


def _in_dask_worker() -> bool:
    try:
        from distributed import get_worker

        get_worker()
        return True
    except (ImportError, ValueError):
        return False


def _file_signature(path: str) -> list[float]:
    try:
        st = os.stat(path)
        return [float(st.st_size), float(st.st_mtime)]
    except OSError:
        return [-1.0, -1.0]


def _remove_stale_temps(directory: Path, stems: list[str]) -> None:
    """Delete temp files a killed writer left for these outputs (lightstage.atomic names them
    `.<stem>.<random>.tmp<suffix>`); only the task that owns the outputs calls this."""
    if not directory.is_dir():
        return
    for stem in stems:
        for p in directory.glob(f".{stem}.*.tmp*"):
            p.unlink(missing_ok=True)


def _reason(e: BaseException) -> str:
    if isinstance(e, LightstageError):
        return str(e)
    text = str(e).strip().splitlines()
    return f"{type(e).__name__}: {text[0][:200]}" if text else type(e).__name__


# ---- the chunk task -------------------------------------------------------------------------------------------
def process_chunk(job: ChunkJob) -> ChunkRecord:
    """Downscale (or read back) every frame of a chunk, accumulate its statistics and thumbnails, and save
    them as the chunk's partial file. Per-frame problems are recorded, never raised."""
    from lightstage.preprocess.downscale import decode_downscale
    from lightstage.preprocess.flare import lit_threshold, thumbnail
    from lightstage.preprocess.stats import StatsAccumulator
    from lightstage.records.processed import (
        HalfRounder,
        processed_ok,
        read_processed_half,
        to_float,
        write_processed,
    )
    from lightstage.tonemap import luminance

    if _in_dask_worker():
        from lightstage.threads import set_library_threads

        set_library_threads(1)
    start, cpu0 = time.perf_counter(), time.process_time()
    work = WorkDir.at(job.work_root)
    view = ViewId(job.group, job.camera)
    cfg = job.config
    partial = _partial_path(work, view, job.index, cfg.stats_key())
    if partial.is_file():
        try:
            with np.load(partial, allow_pickle=False) as d:
                records = json.loads(str(d["records"]))
            return ChunkRecord(
                job.group,
                job.camera,
                job.index,
                problems=tuple((int(k), v) for k, v in records["problems"]),
                seconds=time.perf_counter() - start,
                resumed=True,
            )
        except (OSError, ValueError, KeyError):
            partial.unlink(missing_ok=True)  # unreadable: redo the chunk
    W, H = job.raw_size
    w, h = W // DOWNSCALE, H // DOWNSCALE
    _remove_stale_temps(
        work.frame(FrameId(job.group, job.camera, 0)).parent, [f"{lt:03d}" for lt in job.lights]
    )
    _remove_stale_temps(partial.parent, [partial.stem])
    acc = StatsAccumulator(h, w, job.cutoff)
    rounder = HalfRounder(h, w)
    thumbs, sthumbs, taus = [], [], []
    problems: list[tuple[int, str]] = []
    processed = reused = 0
    gains = job.intensities or ((1.0, 1.0, 1.0),) * len(job.lights)
    for light, raw, gain in zip(job.lights, job.raw_paths, gains, strict=True):
        out = work.frame(FrameId(job.group, job.camera, light))
        try:
            if processed_ok(out, (w, h)):
                rgb_h, sat = read_processed_half(out, (w, h))
                rgb32 = to_float(rgb_h)
                reused += 1
            else:
                small = decode_downscale(raw, (W, H), job.cutoff, cfg.band_rows)
                rgb32, sat = small.rgb, small.saturated
                if job.exposure_scale != 1.0:
                    rgb32 *= np.float32(job.exposure_scale)
                if tuple(gain) != (1.0, 1.0, 1.0):  # equal white lights downstream
                    rgb32 *= (1.0 / np.asarray(gain, np.float64)).astype(np.float32)
                _check_finite(rgb32, raw)
                write_processed(
                    out, rounder(rgb32), sat, cfg.compression
                )  # rgb32 now holds the stored values
                processed += 1
            lum = luminance(rgb32)
            th = thumbnail(lum, sat, cfg.flare_thumb)
            tau = lit_threshold(th, job.cutoff, cfg.lit_ratio, cfg.lit_floor)
            acc.add(light, rgb32, sat, tau, lum)
            thumbs.append(th.lum)
            sthumbs.append(th.saturated.astype(np.float16))
            taus.append(tau)
        except Exception as e:  # noqa: BLE001 - one bad frame must not stop the batch
            if isinstance(e, MemoryError | KeyboardInterrupt):
                raise
            problems.append((light, _reason(e)))
    stats = acc.finish()
    records = {"problems": problems, "processed": processed, "reused": reused}
    th_shape = _thumb_shape(h, w, cfg.flare_thumb)
    stats.save(
        partial,
        extras={
            "thumbs": np.stack(thumbs) if thumbs else np.zeros((0, *th_shape), np.float32),
            "sthumbs": np.stack(sthumbs) if sthumbs else np.zeros((0, *th_shape), np.float16),
            "taus": np.asarray(taus, np.float64),
            "records": np.array(json.dumps(records)),
        },
    )
    return ChunkRecord(
        job.group,
        job.camera,
        job.index,
        processed,
        reused,
        tuple(problems),
        time.perf_counter() - start,
        time.process_time() - cpu0,
    )


def _check_finite(rgb: np.ndarray, raw: str) -> None:
    """Refuse a frame with NaN/Inf samples or processed values beyond the half range (one SIMD min/max pass,
    NaN propagates; an area mean is non-finite when any of its sources is)."""
    import torch

    lo, hi = torch.aminmax(torch.from_numpy(rgb))
    if not (-65504.0 <= float(lo) and float(hi) <= 65504.0):
        bad = int(np.count_nonzero(~np.isfinite(rgb)))
        big = int(np.count_nonzero(np.abs(np.nan_to_num(rgb)) > 65504.0))
        raise LightstageError(
            f"{raw}: non-finite pixels ({bad} NaN/Inf processed samples, {big} beyond the half range)"
        )


def _thumb_shape(h: int, w: int, factor: int) -> tuple[int, int]:
    return (max(1, h // factor), max(1, w // factor))


# ---- the view task --------------------------------------------------------------------------------------------
def process_view(job: ViewJob, chunk_records: list[ChunkRecord] | None = None) -> ViewRecord:
    """Merge a view's chunk partials (tree), segment, score flares, write the view's outputs; view.json
    last. `chunk_records` (from this run's chunk tasks) only feed the record's timings."""
    from lightstage.frames import write_exr, write_image
    from lightstage.preprocess.flare import flare_scores
    from lightstage.preprocess.segment import iou, mask_flags, segment_view, zone_map
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
    paths = [_partial_path(work, view, i, key) for i in range(job.chunks)]
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

    stats = merge_tree(parts()) or empty_stats(h, w)
    if stats.count == 0:
        stats = empty_stats(h, w)
    if stats.mean.shape[:2] != (h, w):
        raise LightstageError(
            f"{view}: statistics are {stats.mean.shape[1]}x{stats.mean.shape[0]}, expected {w}x{h}"
        )
    mask, seg_info = segment_view(stats, cfg)
    zones = zone_map(mask, cfg.band_width)
    lum_thumbs = np.concatenate(thumbs) if thumbs else np.zeros((0, 1, 1), np.float32)
    sat_thumbs = np.concatenate(sthumbs) if sthumbs else np.zeros((0, 1, 1), np.float32)
    scores = flare_scores(lum_thumbs, sat_thumbs, mask, cfg.flare_dilate, job.cutoff, cfg.flare_thumb)
    lights = list(stats.lights)
    rejected = [lt for lt, s in zip(lights, scores, strict=True) if s > cfg.flare_threshold]
    level = _foreground_level(stats.mean, mask, cfg.exposure_percentile)
    gt_iou = None
    if job.gt_mask and Path(job.gt_mask).is_file():
        gt_iou = iou(mask, read_gt_mask(job.gt_mask, (w, h)))
    sfm, sfm_lights = _sfm_image(work, job, set(lights) - set(rejected))
    sfm_mask = upsample_mask(mask, (sfm.shape[1], sfm.shape[0])) > 0
    sfm_level = _foreground_level(sfm, sfm_mask, cfg.exposure_percentile)

    vdir = work.view_dir(view)
    _remove_stale_temps(vdir, ["stats", "mean", "sfm", "mask", "zones", "view"])
    stats.save(
        vdir / "stats.npz",
        extras={
            "mask": mask,
            "flare_scores": np.asarray(scores, np.float32),
            "lit_thresholds": np.concatenate(taus) if taus else np.zeros(0),
        },
    )
    write_exr(work.mean_image(view), to_half(stats.mean), compression="zip")
    write_exr(work.sfm_hdr(view), to_half(sfm), compression="zip")
    write_image(work.mask(view), (mask * 255).astype(np.uint8))
    write_image(work.zones(view), zones)
    record = ViewRecord(
        group=job.group,
        camera=job.camera,
        key=cfg.view_key(),
        lights=lights,
        problems=problems,
        problem_files={
            lt: _file_signature(p)
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
    )
    write_json_atomic(vdir / VIEW_RECORD, asdict(record))
    for p in paths:
        p.unlink(missing_ok=True)
    try:
        (vdir / PARTIALS).rmdir()
    except OSError:
        pass
    return record


def _foreground_level(rgb: np.ndarray, mask: np.ndarray, percentile: float) -> float:
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
    )
    try:
        return sfm_mean_image(src, cfg.sfm_trim), chosen
    except LightstageError as e:
        raise LightstageError(f"{view}: SfM image: {e}") from None


def read_gt_mask(path: str | os.PathLike[str], size: tuple[int, int]) -> np.ndarray:
    """A full-resolution ground-truth mask PNG, area-downscaled to `size` (w, h): foreground where more than
    half of the source pixels are (strict majority)."""
    import cv2

    from lightstage.frames import read_image

    img = read_image(path)[..., 0]
    m = img > 0.5 * (255.0 if img.max() > 1.0 else 1.0)
    return cv2.resize(m.astype(np.float32), size, interpolation=cv2.INTER_AREA) > 0.5


def _view_finished(work: WorkDir, job: ViewJob) -> ViewRecord | None:
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
    for lt in record.lights:
        if not processed_ok(work.frame(FrameId(job.group, job.camera, lt)), job.size):
            return None
    for lt, raw in zip(job.lights, job.raw_paths, strict=False):  # a bad frame whose raw file changed
        sig = record.problem_files.get(str(lt))
        if sig is not None and _file_signature(raw) != sig:
            return None
    if set(record.lights) | {int(k) for k in record.problems} != set(job.lights):
        return None
    return record


# ---- orchestration --------------------------------------------------------------------------------------------
def run_preprocess(
    work: WorkDir, config: PreprocessConfig, client: Any = None, progress: bool = True
) -> dict[str, Any]:
    """Preprocess the capture named in WORK/capture.txt into WORK/preprocess; returns a summary dict."""
    t0 = time.perf_counter()
    if isinstance(config, dict):
        config = PreprocessConfig.from_dict(config)
    config.validate()
    capture = open_capture(work.capture_path())
    stage = capture.stage
    if stage.width % DOWNSCALE or stage.height % DOWNSCALE:
        raise LightstageError(
            f"{capture.root / 'stage.yaml'}: resolution {stage.width}x{stage.height} is not a multiple of {DOWNSCALE}"
        )
    size = (stage.width // DOWNSCALE, stage.height // DOWNSCALE)
    lights = [lt.index for lt in stage.lights]
    intensities = {lt.index: tuple(float(x) for x in lt.intensity) for lt in stage.lights}
    view_jobs: list[ViewJob] = []
    chunk_jobs: dict[ViewId, list[ChunkJob]] = {}
    for view in capture.views():
        raw = tuple(str(capture.frame_path(FrameId(view.group, view.camera, lt))) for lt in lights)
        gt = GroundTruth.of(capture.root).mask(view)
        chunks = _chunks(lights, config.chunk_lights)
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
            )
            for i, c in enumerate(chunks)
        ]

    records: dict[ViewId, ViewRecord] = {}
    todo: list[ViewJob] = []
    for job in view_jobs:
        done = _view_finished(work, job)
        if done is not None:
            records[done.view] = done
        else:
            todo.append(job)
    finished_before = len(records)
    errors: list[str] = []
    chunk_results: list[ChunkRecord] = []
    t_frames = time.perf_counter()
    if client is None:
        _run_local(todo, chunk_jobs, records, chunk_results, errors, progress)
    else:
        _run_dask(client, todo, chunk_jobs, records, chunk_results, errors, config, progress)
    t_views = time.perf_counter() - t_frames
    _add_group_flags(work, records, config)
    t_prev = time.perf_counter()
    exposure = write_previews(
        work, [v for v in view_jobs if ViewId(v.group, v.camera) in records], records, config
    )
    report = build_report(
        work, capture, config, view_jobs, records, chunk_results, errors, finished_before, exposure
    )
    t_previews = time.perf_counter() - t_prev
    from lightstage.preprocess.probe import run_probe

    probe = run_probe(work, capture, client, progress)
    if probe is not None:
        report["probe"] = probe
    report["timings"] = {
        "total_s": round(time.perf_counter() - t0, 3),
        "frames_and_views_s": round(t_views, 3),
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
    summary["problems"] = len(report["problems"])
    summary["errors"] = len(errors)
    summary["report"] = str(work.report("preprocess"))
    return summary


def _add_group_flags(work: WorkDir, records: dict[ViewId, ViewRecord], config: PreprocessConfig) -> None:
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


def _bar(total: int, desc: str, enabled: bool) -> Any:
    from tqdm import tqdm

    return tqdm(total=total, desc=desc, unit="frame", disable=not enabled, dynamic_ncols=True)


def _run_local(
    todo: list[ViewJob],
    chunk_jobs: dict[ViewId, list[ChunkJob]],
    records: dict[ViewId, ViewRecord],
    chunk_results: list[ChunkRecord],
    errors: list[str],
    progress: bool,
) -> None:
    bar = _bar(sum(len(j.lights) for j in todo), "preprocess", progress)
    try:
        for job in todo:
            view = ViewId(job.group, job.camera)
            mine = []
            try:
                for cj in chunk_jobs[view]:
                    mine.append(process_chunk(cj))
                    bar.update(len(cj.lights))
                chunk_results.extend(mine)
                rec = process_view(job, mine)
                records[view] = rec
            except (LightstageError, OSError) as e:
                errors.append(f"{view}: {_reason(e)}")
    finally:
        bar.close()


def _run_dask(
    client: Any,
    todo: list[ViewJob],
    chunk_jobs: dict[ViewId, list[ChunkJob]],
    records: dict[ViewId, ViewRecord],
    chunk_results: list[ChunkRecord],
    errors: list[str],
    config: PreprocessConfig,
    progress: bool,
) -> None:
    """Chunks as tasks; each view's merge task depends on its chunks. Views are admitted in a bounded
    window so partial files (and scheduler state) stay bounded."""
    import uuid

    from distributed import as_completed

    from lightstage.pipelines.cluster import total_threads

    slots = total_threads(client)
    window_chunks = config.window or 4 * slots
    prefix = f"preprocess-{uuid.uuid4().hex[:8]}"
    bar = _bar(sum(len(j.lights) for j in todo), "preprocess", progress)
    pending = iter(todo)
    queue = as_completed()
    in_flight: dict[str, tuple[ViewJob, list[Any]]] = {}
    chunks_in_flight = 0

    def admit() -> bool:
        nonlocal chunks_in_flight
        job = next(pending, None)
        if job is None:
            return False
        view = ViewId(job.group, job.camera)
        tag = f"{prefix}-{job.group}-{job.camera}"
        futs = [
            client.submit(process_chunk, cj, key=f"{tag}-chunk{cj.index}", retries=1, pure=False)
            for cj in chunk_jobs[view]
        ]
        vf = client.submit(_view_after_chunks, job, futs, key=f"{tag}-view", retries=1, pure=False)
        in_flight[vf.key] = (job, futs)
        chunks_in_flight += len(futs)
        queue.add(vf)
        return True

    while chunks_in_flight < window_chunks and admit():
        pass
    try:
        for vf in queue:
            job, futs = in_flight.pop(vf.key)
            chunks_in_flight -= len(futs)
            view = ViewId(job.group, job.camera)
            try:
                rec = vf.result()
                records[view] = rec
                chunk_results.extend(ChunkRecord(**c) for c in rec.chunks)
            except Exception as e:  # noqa: BLE001 - one failed view must not stop the batch
                errors.append(f"{view}: {_reason(e)}")
            for f in futs:
                f.release()
            vf.release()
            bar.update(len(job.lights))
            while chunks_in_flight < window_chunks and admit():
                pass
    except BaseException:
        for job_futs in in_flight.values():
            for f in job_futs[1]:
                f.cancel()
        raise
    finally:
        bar.close()


def _view_after_chunks(job: ViewJob, chunk_records: list[ChunkRecord]) -> ViewRecord:
    """Dask entry point: runs once the view's chunk tasks are done (their records are the argument)."""
    if _in_dask_worker():
        from lightstage.threads import set_library_threads

        set_library_threads(1)
    return process_view(job, list(chunk_records))


# ---- previews and report ----------------------------------------------------------------------------------------
def write_previews(
    work: WorkDir, jobs: list[ViewJob], records: dict[ViewId, ViewRecord], config: PreprocessConfig
) -> float:
    """Write wellit.png (8-bit tonemapped mean image), overlay.png, and the SfM image (sfm.png) with its mask
    (sfm_mask.png) for every finished view, with one exposure for the whole capture per kind of image (and
    WORK/preprocess/sfm_images.json); views whose previews already use those exposures are skipped."""
    from lightstage.frames import read_exr, write_image
    from lightstage.preprocess.segment import overlay, read_mask, zone_map
    from lightstage.preprocess.sfm_image import sfm_image_factor, spread_lights, upsample_mask
    from lightstage.tonemap import tonemap_u8

    def auto(levels: list[float]) -> float:
        levels = [x for x in levels if x > 0]
        return float(np.float32(config.exposure or (1.0 / float(np.median(levels)) if levels else 1.0)))

    exposure = auto([r.exposure_level for r in records.values()])
    sfm_exposure = auto([r.sfm_level for r in records.values()])
    book_path = work.preprocess_dir / PREVIEWS
    _remove_stale_temps(work.preprocess_dir, [Path(PREVIEWS).stem, work.sfm_info.stem])
    _remove_stale_temps(work.report("preprocess").parent, ["preprocess"])
    try:
        book = json.loads(book_path.read_text()) if book_path.is_file() else {}
    except (OSError, ValueError):
        book = {}
    changed = False
    for job in jobs:
        view = ViewId(job.group, job.camera)
        rec = records[view]
        stamp = {
            "exposure": exposure,
            "sfm_exposure": sfm_exposure,
            "view_key": rec.key,
            "lights": len(rec.lights),
            "flags": rec.flags,
        }
        outputs = (
            work.wellit(view),
            work.view_dir(view) / "overlay.png",
            work.sfm_image(view),
            work.sfm_mask(view),
        )
        _remove_stale_temps(work.view_dir(view), [p.stem for p in outputs])
        if book.get(str(view)) == stamp and all(p.is_file() for p in outputs):
            continue
        img = tonemap_u8(read_exr(work.mean_image(view)).astype(np.float32), exposure)
        mask = read_mask(work.mask(view))
        write_image(outputs[0], img)
        write_image(outputs[1], overlay(img, mask, zone_map(mask, config.band_width), rec.flags))
        sfm = read_exr(work.sfm_hdr(view)).astype(np.float32)
        write_image(outputs[2], tonemap_u8(sfm, sfm_exposure))
        write_image(outputs[3], upsample_mask(mask, (sfm.shape[1], sfm.shape[0])))
        book[str(view)] = stamp
        changed = True
    if changed:
        write_json_atomic(book_path, book)
    if jobs:
        W, H = jobs[0].raw_size
        f = sfm_image_factor(W, H, config.sfm_max_side)
        # the lights each view's image is built from, before its own bad and rejected frames are left out
        lights = len(spread_lights(list(jobs[0].lights), config.sfm_lights))
        info = {"factor": f, "size": [W // f, H // f], "lights": lights, "exposure": sfm_exposure}
        write_json_atomic(work.sfm_info, info)
    return exposure


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
    """The stage report: counts, problems, flare scores, rejects, flagged views, segmentation IoU."""
    n_lights = len(capture.stage.lights)
    problems, rejected, flagged, scores, ious = [], [], [], {}, {}
    masks_flagged: list[dict[str, Any]] = []
    for job in jobs:
        view = ViewId(job.group, job.camera)
        rec = records.get(view)
        if rec is None:
            continue
        for lt, reason in sorted(rec.problems.items(), key=lambda kv: int(kv[0])):
            problems.append({"frame": str(FrameId(view.group, view.camera, int(lt))), "reason": reason})
        rejected.extend(str(FrameId(view.group, view.camera, lt)) for lt in rec.rejected)
        scores[str(view)] = rec.flare_scores
        lost = len(rec.problems) + len(rec.rejected)
        if n_lights and lost / n_lights > config.max_lost_fraction:
            flagged.append(
                {
                    "view": str(view),
                    "lost": lost,
                    "bad": len(rec.problems),
                    "rejected": len(rec.rejected),
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
        "rejected": len(rejected),
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
        "exposure": exposure,
        "counts": counts,
        "problems": problems,
        "rejected_frames": rejected,
        "flagged_views": flagged,
        "flagged_masks": masks_flagged,
        "flare": {"threshold": config.flare_threshold, "scores": scores},
        "warnings": [f"view {f['view']} lost {f['lost']} of {n_lights} frames" for f in flagged]
        + [f"view {f['view']}: suspicious mask: {'; '.join(f['reasons'])}" for f in masks_flagged],
        "errors": errors,
    }
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
