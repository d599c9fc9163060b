"""The chunk task: decode (or read back) each raw frame of a few lights of one view once, write its processed
frame, and stream it into the chunk's partial statistics and flare thumbnails (saved atomically)."""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

from lightstage.atomic import atomic_path
from lightstage.dask_executor import in_dask_worker
from lightstage.errors import EnvironmentFault, LightstageError, is_environment_error
from lightstage.exr_header import prefetch_file
from lightstage.frames import pixel_verdict
from lightstage.ids import FrameId, ViewId
from lightstage.npyio import load_npz
from lightstage.preprocess.decoder_choice import process_chooser
from lightstage.preprocess.downscale import Downscaled, decode_downscale_factors, decode_raw, downscale
from lightstage.preprocess.jobs import (
    ChunkJob,
    ChunkRecord,
    partial_path,
    reason_of,
    remove_stale_temps,
    sfm_frame_path,
)
from lightstage.workdir import DOWNSCALE, WorkDir


# ---- the chunk task -------------------------------------------------------------------------------------------
def process_chunk(job: ChunkJob) -> ChunkRecord:
    """Downscale (or read back) every frame of a chunk, accumulate its statistics and thumbnails, and save
    them as the chunk's partial file. Content problems of a frame are recorded, never raised; a fault of the
    environment (lightstage.errors.EnvironmentFault: permission, disk full, I/O error, a stalled read) fails the
    task before its partial is saved, so nothing of it is remembered and a retry or a rerun redoes the chunk."""
    from lightstage.preprocess.flare import lit_threshold, thumbnail
    from lightstage.preprocess.stats import StatsAccumulator

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
            records = json.loads(str(load_npz(partial, ["records"])["records"]))
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
    remove_stale_temps(
        partial.parent, [partial.stem, *(sfm_frame_path(work, view, lt).stem for lt in job.lights)]
    )
    acc = StatsAccumulator(h, w, job.cutoff)
    buffers = FrameBuffers(h, w)
    thumbs, sthumbs, taus = [], [], []
    problems: list[tuple[int, str]] = []
    processed = reused = 0
    chooser = process_chooser()
    decoded_before = dict(chooser.counts)
    gains = job.intensities or ((1.0, 1.0, 1.0),) * len(job.lights)
    for light, raw, gain in zip(job.lights, job.raw_paths, gains, strict=True):
        try:
            rgb32, sat, made = frame_for_stats(job, light, raw, gain, buffers)
        except EnvironmentFault:
            raise  # the machine, not the frame: fail the task (retried), never a bad frame
        except Exception as e:  # noqa: BLE001 - one bad frame must not stop the batch
            if isinstance(e, MemoryError | KeyboardInterrupt):
                raise
            if is_environment_error(e):
                raise EnvironmentFault(f"{raw}: {reason_of(e)}") from e
            problems.append((light, reason_of(e)))
            continue
        processed += made
        reused += not made
        lum = buffers.luminance(rgb32)
        th = thumbnail(lum, sat, cfg.flare_thumb, buffers.scratch)
        tau = lit_threshold(th, job.cutoff, cfg.lit_ratio, cfg.lit_floor)
        acc.add(light, rgb32, sat, tau, lum)
        thumbs.append(th.lum)
        sthumbs.append(th.saturated.astype(np.float16))
        taus.append(tau)
    stats = acc.finish(reuse=True)  # saved right away: no copies
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
        decoded={d: n - decoded_before[d] for d, n in chooser.counts.items() if n > decoded_before[d]},
        decoder_probe=chooser.probe_medians() if cfg.decoder == "auto" else {},
    )


class FrameBuffers:
    """The arrays a chunk task makes each of its frames in, allocated once per chunk: on some VMs the kernel's
    cost of fresh memory (page faults, huge-page zeroing) rivals the work done in it (docs/benchmarks.md)."""

    def __init__(self, height: int, width: int) -> None:
        from lightstage.records.processed import HalfRounder

        self.rgb = np.empty((height, width, 3), np.float32)
        self.saturated = np.empty((height, width), bool)
        self.rounder = HalfRounder(height, width)
        self.lum = np.empty((height, width), np.float32)
        self.scratch = np.empty((height, width), np.float32)  # flare.thumbnail's flags

    def luminance(self, rgb: np.ndarray) -> np.ndarray:
        """`lightstage.tonemap.luminance` of a frame, into the reused luminance buffer."""
        import cv2

        from lightstage.tonemap import LUMA

        return cv2.transform(
            np.ascontiguousarray(rgb, np.float32), np.array([LUMA], np.float32), dst=self.lum
        )


def frame_for_stats(
    job: ChunkJob, light: int, raw: str, gain: tuple[float, float, float], buffers: FrameBuffers
) -> tuple[np.ndarray, np.ndarray, bool]:
    """One frame of the chunk as the statistics see it: ((h, w, 3) float32 as stored, (h, w) saturated, True
    when it was made now; a decoded frame lives in `buffers` until the next). A valid processed frame is read
    back; otherwise the raw frame is decoded, judged (pixel policy), scaled, written, and for an SfM light also
    downscaled to the SfM image's resolution. Content errors raise a LightstageError naming the raw file;
    failing to write is an EnvironmentFault."""
    from lightstage.records.processed import processed_ok, read_processed_half, to_float, write_processed

    cfg, work = job.config, WorkDir.at(job.work_root)
    W, H = job.raw_size
    size = (W // DOWNSCALE, H // DOWNSCALE)
    out = work.frame(FrameId(job.group, job.camera, light))
    if processed_ok(out, size):
        try:
            rgb_h, sat = read_processed_half(out, size)
            return to_float(rgb_h), sat, False
        except EnvironmentFault:
            raise
        except LightstageError:
            pass  # our own output is unreadable: make it again from the raw frame
    small, sfm = decode_frame(job, raw, light in job.sfm_lights, (buffers.rgb, buffers.saturated))
    verdict = pixel_verdict(small.non_finite, small.negative)
    if not verdict.ok:
        raise LightstageError(f"{raw}: {verdict.status.replace('_', '-')} pixels ({verdict.message})")
    rgb32, sat = small.rgb, small.saturated
    if job.exposure_scale != 1.0:
        rgb32 *= np.float32(job.exposure_scale)
    if tuple(gain) != (1.0, 1.0, 1.0):  # equal white lights downstream
        # each row times the per-channel scales tiled along it: numpy's broadcast multiply over the last
        # axis of 3 (the same float32 products) runs 10x slower
        scale = (1.0 / np.asarray(gain, np.float64)).astype(np.float32)
        rows = rgb32.reshape(rgb32.shape[0], -1)
        np.multiply(rows, np.tile(scale, rgb32.shape[1]), out=rows)
    check_finite(rgb32, raw)
    try:
        write_processed(
            out, buffers.rounder(rgb32), sat, cfg.compression
        )  # rgb32 now holds the stored values
        if sfm is not None:
            save_array_atomic(sfm_frame_path(work, ViewId(job.group, job.camera), light), sfm)
    except Exception as e:  # noqa: BLE001 - our outputs, not the raw frame: the disk or the directory failed
        raise EnvironmentFault(f"{out}: cannot write ({reason_of(e)})") from None
    return rgb32, sat, True


def decode_frame(
    job: ChunkJob, raw: str, for_sfm: bool, out: tuple[np.ndarray, np.ndarray] | None = None
) -> tuple[Downscaled, np.ndarray | None]:
    """Decode a raw frame (read first within the read timeout) into its processed-size downscale (into `out`'s
    rgb and saturation arrays when given) and, when `for_sfm`, its downscale at the SfM image's factor
    (x exposure_scale, as sfm_image.sfm_mean_image makes it), both from one decode, with the configured
    decoder or the one this process measured cheaper (`auto`, preprocess.decoder_choice)."""
    cfg = job.config
    prefetch_file(raw, cfg.read_timeout_s)
    factors = (DOWNSCALE, job.sfm_factor) if for_sfm and job.sfm_factor < DOWNSCALE else (DOWNSCALE,)

    def decode(decoder: str) -> list[Downscaled]:
        if decoder == "bands":
            return decode_downscale_factors(raw, job.raw_size, job.cutoff, cfg.band_rows, factors, out)
        pixels = decode_raw(raw, job.raw_size)
        return [
            downscale(pixels, job.cutoff, cfg.band_rows, f, out if f == DOWNSCALE else None) for f in factors
        ]

    outs, _ = process_chooser().run(cfg.decoder, decode)
    if len(outs) == 1:
        return outs[0], None
    sfm = outs[1].rgb
    sfm *= np.float32(job.exposure_scale)
    return outs[0], sfm


def save_array_atomic(path: Path, array: np.ndarray) -> None:
    """np.save through a temp file and a rename (lightstage.atomic), so a killed task leaves no partial file."""
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        np.save(f, array, allow_pickle=False)


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
