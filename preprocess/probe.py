"""Image measurements of a mirror-ball probe capture (see capture/probe.py): the ball's outline and, per light,
the sub-pixel position of the light's reflection — in raw pixels, so calibration never reads raw frames.

Per (position, camera) one task reads the ambient frame and every OLAT frame of that view and writes
`WORK/preprocess/probe/<position>/<camera>.json` atomically (resumable: a view whose record matches its input
files is skipped). Calibration (`calibration/probe.py`) turns the outlines into ball centres and the highlights
into rays towards the lights.
"""

from __future__ import annotations

import json
import os
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import cv2
import numpy as np

from lightstage.atomic import write_json_atomic
from lightstage.errors import LightstageError
from lightstage.executor import Executor, LoopExecutor

if TYPE_CHECKING:
    from lightstage.capture.layout import Capture
    from lightstage.capture.probe import ProbeInfo
    from lightstage.workdir import WorkDir

MAX_OUTLINE_POINTS = 2048  # outline points kept per view (evenly spaced): plenty for a centre to 0.01 px
RECORD_VERSION = 1


@dataclass(frozen=True)
class ProbeViewJob:
    """Inputs of one probe view task (picklable)."""

    out: str  # the view's JSON record
    position: str
    camera: str
    ambient: str  # raw ambient frame
    frames: tuple[tuple[int, str], ...]  # (light index, raw OLAT frame)
    size: tuple[int, int]  # raw (width, height)
    saturation: float
    exposure_scale: float = 1.0
    min_snr: float = 20.0  # a highlight's peak over the noise std
    window_px: int = 4  # centroid window half-size (raw pixels)


@dataclass
class ProbeViewRecord:
    """What one view's frames show: the ball outline and each light's highlight (raw pixels, centres i + 0.5)."""

    position: str
    camera: str
    outline: list[list[float]] = field(default_factory=list)  # (N, 2) u, v on the ball's half-level contour
    disc: list[float] = field(default_factory=list)  # rough u, v, radius of the ball (pixels)
    highlights: dict[str, list[float]] = field(default_factory=dict)  # light -> [u, v, peak / noise]
    missing: dict[str, str] = field(default_factory=dict)  # light -> why no highlight was taken
    error: str | None = None  # the view could not be measured (e.g. no ball in the ambient frame)
    inputs: list[list[float]] = field(default_factory=list)  # (size, mtime) of the input files, for resuming
    seconds: float = 0.0
    version: int = RECORD_VERSION


def _luminance(rgb: np.ndarray) -> np.ndarray:
    from lightstage.tonemap import luminance

    return luminance(rgb)


def ball_outline(lum: np.ndarray) -> tuple[np.ndarray, tuple[float, float, float]]:
    """The lit ball's outline in an ambient frame: (N, 2) sub-pixel (u, v) points of the contour halfway
    between the ball's level and the background just outside it, and a rough (u, v, radius) of the disc.

    The ball is the largest bright component; the half level of a blurred edge lies on the true edge for any
    symmetric blur, so the contour is unbiased to well under 0.1 px."""
    from skimage.measure import find_contours

    bg = float(np.median(lum))
    noise = 1.4826 * float(np.median(np.abs(lum - bg)))
    top = float(np.percentile(lum, 99.9))
    if top - bg <= 20.0 * noise + 1e-6:
        raise LightstageError("no bright ball in the ambient frame")
    bright = (lum > 0.5 * (bg + top)).astype(np.uint8)
    n, labels, stats, _ = cv2.connectedComponentsWithStats(bright, connectivity=8)
    if n < 2:
        raise LightstageError("no bright ball in the ambient frame")
    k = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
    x0, y0, w, h = (
        int(stats[k, i]) for i in (cv2.CC_STAT_LEFT, cv2.CC_STAT_TOP, cv2.CC_STAT_WIDTH, cv2.CC_STAT_HEIGHT)
    )
    H, W = lum.shape
    if x0 <= 1 or y0 <= 1 or x0 + w >= W - 1 or y0 + h >= H - 1:
        raise LightstageError("the ball touches the image border")
    comp = (labels == k).astype(np.uint8)
    inner = cv2.erode(comp, np.ones((7, 7), np.uint8)) > 0
    ring = (cv2.dilate(comp, np.ones((13, 13), np.uint8)) > 0) & ~(
        cv2.dilate(comp, np.ones((7, 7), np.uint8)) > 0
    )
    if not inner.any() or not ring.any():
        raise LightstageError("the bright blob in the ambient frame is too small to be the ball")
    level = 0.5 * (float(np.median(lum[inner])) + float(np.median(lum[ring])))
    pad = 8
    r0, r1, c0, c1 = max(y0 - pad, 0), min(y0 + h + pad, H), max(x0 - pad, 0), min(x0 + w + pad, W)
    crop = lum[r0:r1, c0:c1].astype(np.float64)
    contours = [c for c in find_contours(crop, level) if len(c) > 8 and np.allclose(c[0], c[-1])]
    if not contours:
        raise LightstageError("the ball's outline is not a closed contour")
    c = max(contours, key=len)[:-1]
    uv = np.stack([c[:, 1] + c0 + 0.5, c[:, 0] + r0 + 0.5], axis=1)
    centre = uv.mean(axis=0)
    radius = float(np.sqrt(stats[k, cv2.CC_STAT_AREA] / np.pi))
    return uv, (float(centre[0]), float(centre[1]), radius)


def highlight_window(
    disc: tuple[float, float, float], shape: tuple[int, int], window_px: int = 4
) -> tuple[int, int, int, int]:
    """Rows r0:r1 and columns c0:c1 of an (H, W) frame that `ball_highlight` looks at: the disc and a margin."""
    u0, v0, rad = disc
    H, W = shape
    m = int(np.ceil(rad)) + window_px + 2
    return max(int(v0) - m, 0), min(int(v0) + m + 1, H), max(int(u0) - m, 0), min(int(u0) + m + 1, W)


def ball_highlight(
    lum: np.ndarray,
    disc: tuple[float, float, float],
    saturation: float,
    min_snr: float = 20.0,
    window_px: int = 4,
    origin: tuple[int, int] | None = None,
) -> tuple[float, float, float]:
    """The light's reflection on the ball: the background-subtracted intensity centroid (u, v) in a window
    around the brightest pixel on the disc, and its peak over the noise std. A LightstageError says why there
    is none: too faint, clipped (the centroid of a clipped spot is not its centre), or a second spot.
    `origin`: (row, column) of `lum` in the frame when `lum` is only the frame's `highlight_window`."""
    u0, v0, rad = disc
    if origin is None:
        r0, r1, c0, c1 = highlight_window(disc, lum.shape, window_px)
        crop = lum[r0:r1, c0:c1].astype(np.float64)
    else:
        (r0, c0), crop = origin, lum.astype(np.float64)
        r1, c1 = r0 + crop.shape[0], c0 + crop.shape[1]
    rows, cols = np.mgrid[r0:r1, c0:c1]
    on_ball = (cols + 0.5 - u0) ** 2 + (rows + 0.5 - v0) ** 2 <= (rad + 1.0) ** 2
    bg = float(np.median(crop))
    noise = 1.4826 * float(np.median(np.abs(crop - bg))) + 1e-12
    score = np.where(on_ball, crop, -np.inf)
    i, j = np.unravel_index(int(np.argmax(score)), crop.shape)
    snr = (crop[i, j] - bg) / noise
    if snr < min_snr:
        raise LightstageError(f"no highlight (peak {snr:.1f} x noise)")
    w = window_px
    a0, a1, b0, b1 = (
        max(i - w, 0),
        min(i + w + 1, crop.shape[0]),
        max(j - w, 0),
        min(j + w + 1, crop.shape[1]),
    )
    win = crop[a0:a1, b0:b1]
    if (win >= saturation).any():
        raise LightstageError("highlight clipped")
    others = score.copy()
    others[a0:a1, b0:b1] = -np.inf
    if (others.max() - bg) > 0.3 * (crop[i, j] - bg):
        raise LightstageError("a second bright spot on the ball")
    wts = np.clip(win - bg, 0.0, None)
    total = float(wts.sum())
    rr, cc = np.mgrid[a0:a1, b0:b1]
    u = float((wts * (cc + 0.5)).sum() / total) + c0
    v = float((wts * (rr + 0.5)).sum() / total) + r0
    return u, v, float(snr)


def _signature(paths: list[str]) -> list[list[float]]:
    out = []
    for p in paths:
        try:
            st = os.stat(p)
            out.append([float(st.st_size), float(st.st_mtime)])
        except OSError:
            out.append([-1.0, -1.0])
    return out


def _read_lum(
    path: str, size: tuple[int, int], exposure_scale: float, window: tuple[int, int, int, int] | None = None
) -> np.ndarray:
    """Luminance of a raw frame, or of its rows r0:r1 and columns c0:c1 (`window`): only those are converted
    to float32 (through PyTorch; numpy's half conversion cost more than the decode)."""
    from lightstage.frames import read_exr
    from lightstage.records.processed import to_float

    rgb = read_exr(path, size)
    if window is not None:
        r0, r1, c0, c1 = window
        rgb = rgb[r0:r1, c0:c1]
    rgb = to_float(rgb) if rgb.dtype == np.float16 else np.ascontiguousarray(rgb, np.float32)
    if exposure_scale != 1.0:
        rgb *= np.float32(exposure_scale)
    return _luminance(rgb)


def measure_probe_view(job: ProbeViewJob) -> ProbeViewRecord:
    """Measure one view's outline and highlights and write its record (atomically); returns the record."""
    t0 = time.perf_counter()
    rec = ProbeViewRecord(job.position, job.camera)
    rec.inputs = _signature([job.ambient, *(p for _, p in job.frames)])
    try:
        outline, disc = ball_outline(_read_lum(job.ambient, job.size, job.exposure_scale))
    except LightstageError as e:
        rec.error = f"{job.ambient}: {e}"
    else:
        step = max(1, int(np.ceil(len(outline) / MAX_OUTLINE_POINTS)))
        rec.outline = np.round(outline[::step], 4).tolist()
        rec.disc = [round(x, 3) for x in disc]
        window = highlight_window(disc, (job.size[1], job.size[0]), job.window_px)
        for light, path in job.frames:
            try:
                u, v, snr = ball_highlight(
                    _read_lum(path, job.size, job.exposure_scale, window),
                    disc,
                    job.saturation,
                    job.min_snr,
                    job.window_px,
                    origin=(window[0], window[2]),
                )
            except LightstageError as e:
                rec.missing[str(light)] = str(e)
                continue
            rec.highlights[str(light)] = [round(u, 5), round(v, 5), round(snr, 1)]
    rec.seconds = round(time.perf_counter() - t0, 3)
    write_json_atomic(Path(job.out), asdict(rec))
    return rec


def load_view_record(path: Path) -> ProbeViewRecord | None:
    """A view's record, or None when absent, unreadable or from another version (then it is measured again)."""
    try:
        d = json.loads(path.read_text())
        if d.get("version") != RECORD_VERSION:
            return None
        return ProbeViewRecord(**d)
    except (OSError, ValueError, TypeError):
        return None


def probe_jobs(work: WorkDir, capture: Capture, info: ProbeInfo) -> list[ProbeViewJob]:
    """One job per (position, camera) of the probe capture `info` (capture.probe.ProbeInfo)."""
    stage = capture.stage
    jobs = []
    for pos in info.positions:
        for cam in stage.camera_ids:
            frames = tuple(
                (lt.index, str(info.frame(capture.root, pos, cam, lt.index))) for lt in stage.lights
            )
            jobs.append(
                ProbeViewJob(
                    str(work.probe_view(pos, cam)),
                    pos,
                    cam,
                    str(info.ambient(capture.root, pos, cam)),
                    frames,
                    (stage.width, stage.height),
                    stage.saturation,
                    capture.info.exposure_scale,
                )
            )
    return jobs


def run_probe(
    work: WorkDir, capture: Capture, executor: Executor | None = None, progress: bool = True
) -> dict[str, Any] | None:
    """Measure every view of the capture's probe (None when it has none); resumes finished views. Returns a
    summary for the preprocess report."""
    from lightstage.capture.probe import load_probe_info

    info = load_probe_info(capture.root)
    if info is None:
        return None
    t0 = time.perf_counter()
    jobs = probe_jobs(work, capture, info)
    records: list[ProbeViewRecord] = []
    todo = []
    for job in jobs:
        done = load_view_record(Path(job.out))
        if done is not None and done.inputs == _signature([job.ambient, *(p for _, p in job.frames)]):
            records.append(done)
        else:
            todo.append(job)
    executor = executor or LoopExecutor()  # its workers have one library thread each
    records += executor.map(measure_probe_view, todo, desc="probe views", unit="view", progress=progress)
    errors = [r.error for r in records if r.error]
    return {
        "positions": list(info.positions),
        "radius_m": info.radius_m,
        "views": len(records),
        "views_measured_now": len(todo),
        "views_without_ball": len(errors),
        "errors": errors[:20],
        "highlights": sum(len(r.highlights) for r in records),
        "highlights_missing": sum(len(r.missing) for r in records),
        "seconds": round(time.perf_counter() - t0, 3),
    }
