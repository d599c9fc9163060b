"""The jobs and records that pass between the preprocess driver (run.py) and its tasks: small, picklable
dataclasses, and the helpers every task shares (partial paths, raw-file signatures, stale temp cleanup)."""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from lightstage.atomic import temp_owner
from lightstage.errors import LightstageError
from lightstage.ids import ViewId
from lightstage.preprocess.config import PreprocessConfig
from lightstage.workdir import DOWNSCALE, WorkDir

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
    # the view's SfM lights (sfm_image.spread_lights) and the SfM image's factor: below DOWNSCALE, the chunk
    # also saves those frames at raw / factor, so the view task need not decode them again
    sfm_lights: tuple[int, ...] = ()
    sfm_factor: int = DOWNSCALE


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
    decoded: dict[str, int] = field(default_factory=dict)  # raw frames decoded now, per decoder
    decoder_probe: dict[str, float] = field(default_factory=dict)  # `auto`: median probe CPU-s per decoder


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
    user_mask: str | None = None  # the capture's own mask of this view (masks/<g>/<c>.png), used as it is
    # per light of `lights`, the processed pixel (u, v) of its image when the light is in view, else None
    # (flare.light_pixels on the nominal stage geometry): only those frames can have a flare
    light_pixels: tuple[tuple[float, float] | None, ...] = ()


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
    # the camera's cross-group step (camera_task.py): pixels removed, noise fitted, IoU of the view's own mask
    consistency: dict[str, Any] = field(default_factory=dict)
    # the capture's own mask, when it has one: {"path", "signature" ([size, mtime]), "iou_own": IoU of the mask
    # preprocess computed against it}; the view's mask is then that mask
    user_mask: dict[str, Any] = field(default_factory=dict)
    # light -> fraction of the frame's pixels in its flare and bulb mask (WorkDir.flare_mask; flare_policy mask)
    flared: dict[str, float] = field(default_factory=dict)
    # light -> mean level of the frame (flare.frame_levels), for the broken-frame test (broken.py); frames whose
    # light is in view are left out
    frame_levels: dict[str, float] = field(default_factory=dict)

    @property
    def view(self) -> ViewId:
        return ViewId(self.group, self.camera)


# ---- helpers ------------------------------------------------------------------------------------------------
def partial_path(work: WorkDir, view: ViewId, index: int, key: str) -> Path:
    """Where chunk `index` of a view saves its partial statistics (`key`: the config's stats_key)."""
    return work.view_dir(view) / PARTIALS / f"chunk{index:04d}-{key}.npz"


def camera_marker(work: WorkDir, camera: str) -> Path:
    """The camera step's marker (camera_task.py): written last, removed by a view task that rewrites a view."""
    return work.preprocess_dir / "cameras" / f"{camera}.json"


def sfm_frame_path(work: WorkDir, view: ViewId, light: int) -> Path:
    """Where a chunk leaves an SfM light's frame at the SfM resolution for its view task (float32 .npy)."""
    return work.view_dir(view) / PARTIALS / f"sfm-{light:03d}.npy"


def split_lights(lights: list[int], size: int) -> list[tuple[int, ...]]:
    """The lights in chunks of `size` (chunk_lights), in order."""
    return [tuple(lights[i : i + size]) for i in range(0, len(lights), size)]


def file_signature(path: str) -> list[float]:
    """[size, mtime] of a raw file ([-1, -1] when it cannot be stat-ed): a bad frame is retried when it changes."""
    try:
        st = os.stat(path)
        return [float(st.st_size), float(st.st_mtime)]
    except OSError:
        return [-1.0, -1.0]


def remove_stale_temps(directory: Path, stems: list[str]) -> None:
    """Delete the temp files killed writers left for these outputs (lightstage.atomic names them
    `.<stem>.<pid>.<random>.tmp<suffix>`): this process's own and those of a process that no longer exists,
    never a live process's (a concurrent run's in-flight file). Only the task that owns the outputs calls this."""
    if not directory.is_dir():
        return
    for stem in stems:
        for p in directory.glob(f".{stem}.*.tmp*"):
            owner = temp_owner(p.name)
            if owner is None or owner == os.getpid() or not _alive(owner):
                p.unlink(missing_ok=True)


def _alive(pid: int) -> bool:
    """Whether a process with this pid exists on this machine (signal 0 checks without sending anything)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True  # exists, owned by another user
    return True


def reason_of(e: BaseException) -> str:
    """One line for a per-frame problem: a LightstageError's message, else the exception type and first line."""
    if isinstance(e, LightstageError):
        return str(e)
    text = str(e).strip().splitlines()
    return f"{type(e).__name__}: {text[0][:200]}" if text else type(e).__name__
