"""The chunk task: decode (or read back) each raw frame of a few lights of one view once, write its processed
frame, and stream it into the chunk's partial statistics and flare thumbnails (saved atomically)."""

from __future__ import annotations

import json
import time

import numpy as np

from lightstage.errors import LightstageError
from lightstage.ids import FrameId, ViewId
from lightstage.preprocess.jobs import (
    ChunkJob,
    ChunkRecord,
    in_dask_worker,
    partial_path,
    reason_of,
    remove_stale_temps,
)
from lightstage.workdir import DOWNSCALE, WorkDir


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

    if in_dask_worker():
        from lightstage.threads import set_library_threads

        set_library_threads(1)
    start, cpu0 = time.perf_counter(), time.process_time()
    work = WorkDir.at(job.work_root)
    view = ViewId(job.group, job.camera)
    cfg = job.config
    partial = partial_path(work, view, job.index, cfg.stats_key())
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
    remove_stale_temps(
        work.frame(FrameId(job.group, job.camera, 0)).parent, [f"{lt:03d}" for lt in job.lights]
    )
    remove_stale_temps(partial.parent, [partial.stem])
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
                check_finite(rgb32, raw)
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
            problems.append((light, reason_of(e)))
    stats = acc.finish()
    records = {"problems": problems, "processed": processed, "reused": reused}
    th_shape = thumb_shape(h, w, cfg.flare_thumb)
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


def check_finite(rgb: np.ndarray, raw: str) -> None:
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


def thumb_shape(h: int, w: int, factor: int) -> tuple[int, int]:
    return (max(1, h // factor), max(1, w // factor))
