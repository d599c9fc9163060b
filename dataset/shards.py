"""Training ray shards: rays sampled by zone from the training images, shuffled across images into fixed-size,
memory-mappable shards (one .npy of RAY_DTYPE each, blocks foreground | band | background) with a manifest
(format version, dtype, counts per zone, sha256 per shard, normalisation); test frames as full images.

Two phases, both parallel through an executor (lightstage.executor): per training view, sample and
compute every frame's rays into a temporary chunk (zone blocks, shuffled); per shard, gather an evenly spread,
interleaved share of every chunk's zone blocks and shuffle it. Memory per task is one chunk or one shard.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from lightstage.atomic import atomic_path, write_json_atomic
from lightstage.dataset.shard_config import ShardConfig
from lightstage.dataset.shard_rays import ViewTask, read_frame, write_view_chunk
from lightstage.errors import LightstageError
from lightstage.executor import Executor, local_executor
from lightstage.ids import FrameId, ViewId
from lightstage.npyio import load_npy
from lightstage.records.processed import read_flare_mask, read_mask, read_zones
from lightstage.records.shards import (
    COMPOSITION,
    MANIFEST,
    RAY_DTYPE,
    SHARD_FORMAT_VERSION,
    ZONE_NAMES,
    ZONES,
    check_file,
    file_sha256,
    load_manifest,
    read_test_index,
    write_test_index,
)
from lightstage.workdir import ZONE_FOREGROUND, WorkDir


# ---- phase B: gather one shard -------------------------------------------------------------------------
@dataclass(frozen=True)
class ShardTask:
    """One shard: which positions of which chunk zone blocks it gathers (given by the global plan)."""

    index: int
    num_shards: int
    per_zone: tuple[int, int, int]  # rays of each zone block in this shard
    totals: tuple[int, int, int]  # N_z: rays of zone z over all chunks (every one goes to some shard)
    chunks: tuple[str, ...]
    chunk_counts: tuple[tuple[int, int, int], ...]
    path: str
    seed: int


def shard_range(k_lo: int, k_hi: int, s: int, S: int) -> tuple[int, int]:
    """(start, count) of shard s's piece of a chunk zone block whose kept rays have global indices [k_lo, k_hi).

    Shard s owns the indices k = s (mod S) (so shards differ by at most one ray of the zone); inside the
    chunk, whose block is already shuffled, those rays are taken as one contiguous piece: the pieces of shards
    0..S-1 tile the block's first k_hi - k_lo rays in order (one sequential read per chunk, each ray read once).
    """
    shards = np.arange(S)
    below = np.maximum(0, (k_lo - shards + S - 1) // S)  # kept k < k_lo with k = shard (mod S)
    upto = np.maximum(0, (k_hi - shards + S - 1) // S)
    counts = upto - below
    return int(counts[:s].sum()), int(counts[s])


def write_shard(task: ShardTask) -> dict[str, Any]:
    """Gather, shuffle and write one shard; return its record (file, rays, zone counts, sha256, bytes)."""
    path = Path(task.path)
    size = sum(task.per_zone)
    if path.is_file() and path.stat().st_size == _npy_size(size):
        sha = file_sha256(path)
        return _shard_record(task, path, sha)
    rng = np.random.default_rng([task.seed, task.index, 7])
    out = []
    offsets = np.zeros(len(ZONES), np.int64)  # start of each chunk's zone block in the global pool
    gathered: list[list[np.ndarray]] = [[] for _ in ZONES]
    for chunk, counts in zip(task.chunks, task.chunk_counts, strict=True):
        data = load_npy(chunk, mmap_mode="r")
        starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
        for zi in range(len(ZONES)):
            a, n = int(offsets[zi]), counts[zi]
            if n:
                start, count = shard_range(a, a + n, task.index, task.num_shards)
                if count:
                    lo = int(starts[zi]) + start
                    gathered[zi].append(np.array(data[lo : lo + count]))
            offsets[zi] += n
        del data
    for zi in range(len(ZONES)):
        b = np.concatenate(gathered[zi]) if gathered[zi] else np.zeros(0, RAY_DTYPE)
        if len(b) != task.per_zone[zi]:
            raise LightstageError(
                f"{path}: planned {task.per_zone[zi]} {ZONE_NAMES[ZONES[zi]]} rays, gathered {len(b)}"
            )
        out.append(b[rng.permutation(len(b))])
    with atomic_path(path) as tmp:
        np.save(tmp, np.concatenate(out))
    return _shard_record(task, path, file_sha256(path))


def _shard_record(task: ShardTask, path: Path, sha: str) -> dict[str, Any]:
    return {
        "file": f"train/{path.name}",
        "rays": int(sum(task.per_zone)),
        "zones": {ZONE_NAMES[z]: int(n) for z, n in zip(ZONES, task.per_zone, strict=True)},
        "sha256": sha,
        "bytes": path.stat().st_size,
    }


def _npy_size(rays: int) -> int:
    import io

    buf = io.BytesIO()
    np.lib.format.write_array_header_1_0(
        buf, np.lib.format.header_data_from_array_1_0(np.zeros(rays, RAY_DTYPE))
    )
    return buf.tell() + rays * RAY_DTYPE.itemsize


# ---- test images -----------------------------------------------------------------------------------------
@dataclass(frozen=True)
class TestTask:
    """One test frame to store as a full image with its camera and light."""

    work: str
    group: str
    camera: str
    light: int
    K: tuple
    R: tuple
    t: tuple
    dist: tuple
    width: int
    height: int
    light_position: tuple
    light_direction: tuple
    path: str
    compress: bool


def write_test_image(task: TestTask) -> dict[str, Any]:
    """shards/test/<g>_<c>_<lll>.npz: rgb (H, W, 3) f16, saturated, mask, zones, K, R, t, dist, light."""
    from lightstage.threads import set_library_threads

    set_library_threads(1)
    path = Path(task.path)
    name = path.name
    if not path.is_file():
        work = WorkDir.at(task.work)
        view = ViewId(task.group, task.camera)
        rgb, sat = read_frame(
            work.frame(FrameId(task.group, task.camera, task.light)), (task.width, task.height)
        )
        zones_p, mask_p = work.zones(view), work.mask(view)
        zones = read_zones(zones_p) if zones_p.is_file() else np.zeros((task.height, task.width), np.uint8)
        if mask_p.is_file():
            mask = read_mask(mask_p)
        else:
            mask = zones == ZONE_FOREGROUND
        flare_p = work.flare_mask(FrameId(task.group, task.camera, task.light))
        arrays = {
            "rgb": np.ascontiguousarray(rgb),
            "saturated": sat,
            "mask": mask,
            "flare": read_flare_mask(flare_p, mask.shape),
            "zones": zones,
            "K": np.array(task.K),
            "R": np.array(task.R),
            "t": np.array(task.t),
            "dist": np.array(task.dist),
            "width": np.int64(task.width),
            "height": np.int64(task.height),
            "light_position": np.array(task.light_position),
            "light_direction": np.array(task.light_direction),
            "group": np.str_(task.group),
            "camera": np.str_(task.camera),
            "light": np.int64(task.light),
        }
        with atomic_path(path) as tmp:
            with open(tmp, "wb") as f:
                (np.savez_compressed if task.compress else np.savez)(f, **arrays)
    # size and sha256 so that whatever reads the image (trainer previews, eval) refuses a truncated or foreign one
    return {
        "file": f"test/{name}",
        "group": task.group,
        "camera": task.camera,
        "light": task.light,
        "bytes": path.stat().st_size,
        "sha256": file_sha256(path),
    }


# ---- driver ------------------------------------------------------------------------------------------------
def _map(fn: Any, items: list[Any], executor: Executor, progress: bool, desc: str) -> list[Any]:
    """Run fn over items through the executor (bounded windows, item order)."""
    return executor.map(fn, items, desc=desc, progress=progress)


def camera_record(camera: Any) -> dict[str, Any]:
    """One view's calibrated camera as the manifest stores it (float64 values, exact through JSON)."""
    return {
        "K": np.asarray(camera.K, np.float64).tolist(),
        "R": np.asarray(camera.R, np.float64).tolist(),
        "t": np.asarray(camera.t, np.float64).reshape(3).tolist(),
        "dist": np.asarray(camera.dist, np.float64).reshape(-1).tolist(),
        "width": int(camera.width),
        "height": int(camera.height),
    }


def light_table(calib: Any, groups: list[str]) -> dict[str, dict[str, list]]:
    """Per group the world positions and directions (omega) of every light, as the manifest stores them."""
    return {
        g: {
            "positions": np.asarray(calib.light_positions[g], np.float64).tolist(),
            "directions": np.asarray(calib.light_directions(g), np.float64).tolist(),
        }
        for g in groups
    }


def _plan_shards(totals: np.ndarray, rays_per_shard: int) -> int:
    """Number of shards: about `rays_per_shard` rays each, every sampled ray kept (shard s holds the rays
    k = s mod S of each zone, so shards differ by at most one ray per zone and keep the global composition)."""
    if int(np.min(totals)) < 1:
        raise LightstageError(f"not enough rays for one shard (per zone fg/band/bg: {totals.tolist()})")
    return max(1, int(round(int(totals.sum()) / rays_per_shard)))


def shard_zone_counts(totals: tuple[int, ...], S: int, s: int) -> tuple[int, int, int]:
    """Rays of each zone in shard s of S: the count of k < N_z with k = s (mod S)."""
    return tuple(max(0, (int(n) - s + S - 1) // S) for n in totals)  # type: ignore[return-value]


def run_shard(
    work: WorkDir, config: ShardConfig, executor: Executor | None = None, progress: bool = True
) -> dict[str, Any]:
    """Write WORK/shards/{train/*.npy, test/*.npz, manifest.json} from the split, calibration, bounds and
    preprocessed frames. Resumable; reports to reports/shard.json. bounds.json is the bounds stage's output
    (the pipeline runs it first); called without one, this computes it first with the default BoundsConfig.
    `executor` None: a local process pool of `config.workers` (0: min(cpu count, 4); 1: in this process)."""
    if executor is not None:
        return _write_shards(work, config, executor, progress)
    with local_executor(config.workers or min(os.cpu_count() or 1, 4)) as own:  # the pool starts on first use
        return _write_shards(work, config, own, progress)


def _write_shards(work: WorkDir, config: ShardConfig, executor: Executor, progress: bool) -> dict[str, Any]:
    """run_shard's work, through `executor`."""
    from lightstage.dataset.bounds import BoundsConfig, load_bounds, run_bounds
    from lightstage.records.calibration import Calibration
    from lightstage.records.split import load_split

    t0 = time.perf_counter()
    root = work.shards_dir
    manifest_path = root / MANIFEST
    split = load_split(work.split)
    calib = Calibration.load(work.calibration)
    if not work.bounds.is_file():  # a standalone call; whether bounds are current is the runner's to decide
        run_bounds(work, BoundsConfig(), executor, progress=progress)
    bounds = load_bounds(work.bounds)
    # what the shards depend on; the preprocess report changes whenever preprocess rewrote frames or masks
    depends = [work.split, work.calibration, work.bounds, work.report("preprocess")]
    inputs_hash = hashlib.sha256(
        b"".join(p.read_bytes() for p in depends if p.is_file())
        + json.dumps({k: v for k, v in asdict(config).items() if k not in ("workers", "force")}).encode()
    ).hexdigest()[:16]
    if manifest_path.is_file() and not config.force:
        m = json.loads(manifest_path.read_text())
        current = m.get("format_version") == SHARD_FORMAT_VERSION  # older formats are rewritten
        if current and m.get("inputs_hash") == inputs_hash and all(_intact(root, s) for s in m["shards"]):
            return _summary(work, m, skipped=True, seconds=time.perf_counter() - t0)
    tmp_dir = root / "tmp"
    plan_path = tmp_dir / "plan.json"
    stale = not plan_path.is_file() or json.loads(plan_path.read_text()).get("inputs_hash") != inputs_hash
    if root.exists() and (config.force or stale):
        shutil.rmtree(root)  # outputs of other inputs (or forced): never mix them with this run's
    tmp_dir.mkdir(parents=True, exist_ok=True)
    write_json_atomic(plan_path, {"inputs_hash": inputs_hash})
    cfg_dict = asdict(config)

    def cam(view: ViewId) -> Any:
        if view not in calib.views:
            raise LightstageError(f"{work.calibration}: no calibration for view {view}")
        return calib.views[view].camera()

    # phase A: one chunk per training view
    views: list[ViewId] = split.train.views()
    cameras = [camera_record(cam(v)) for v in views]  # the rays' camera table (dataset/ray_table.py)
    view_tasks = []
    excluded = split.train.excluded
    for i, v in enumerate(views):
        lights = tuple(
            lt for lt in split.train.groups[v.group][1] if FrameId(v.group, v.camera, lt) not in excluded
        )
        if not lights:
            continue
        c = cameras[i]
        view_tasks.append(
            ViewTask(
                str(work.root), i, v.group, v.camera, lights, c["width"], c["height"], cfg_dict,
                str(tmp_dir / f"view_{i:05d}.npy"),
            )
        )  # fmt: skip
    t_a = time.perf_counter()
    metas = _map(write_view_chunk, view_tasks, executor, progress, "shard: sample views")
    t_a = time.perf_counter() - t_a
    chunk_counts = tuple(tuple(int(x) for x in m["counts"]) for m in metas)
    totals = np.sum(np.array(chunk_counts, np.int64).reshape(-1, 3), axis=0)
    S = _plan_shards(totals, config.rays_per_shard)
    kept = tuple(int(x) for x in totals)  # every sampled ray goes to a shard
    (root / "train").mkdir(parents=True, exist_ok=True)
    shard_tasks = [
        ShardTask(
            s, S, shard_zone_counts(kept, S, s), kept,  # type: ignore[arg-type]
            tuple(t.chunk for t in view_tasks), chunk_counts,
            str(root / "train" / f"shard_{s:05d}.npy"), config.seed,
        )
        for s in range(S)
    ]  # fmt: skip
    t_b = time.perf_counter()
    records = _map(write_shard, shard_tasks, executor, progress, "shard: write shards")
    t_b = time.perf_counter() - t_b
    # test images
    test_tasks = []
    (root / "test").mkdir(parents=True, exist_ok=True)
    for f in split.test.frames():
        v = ViewId(f.group, f.camera)
        c = cam(v)
        test_tasks.append(
            TestTask(
                str(work.root), f.group, f.camera, f.light,
                c.K.tolist(), c.R.tolist(), c.t.tolist(), np.asarray(c.dist).tolist(), c.width, c.height,
                calib.light_positions[f.group][f.light].tolist(), calib.light_directions(f.group)[f.light].tolist(),
                str(root / "test" / f"{f.group}_{f.camera}_{f.light:03d}.npz"), config.compress_test,
            )
        )  # fmt: skip
    t_c = time.perf_counter()
    tests = _map(write_test_image, test_tasks, executor, progress, "shard: test images")
    t_c = time.perf_counter() - t_c
    write_test_index(root, tests)
    rays = int(sum(r["rays"] for r in records))
    nbytes = int(sum(r["bytes"] for r in records))
    manifest = {
        "format_version": SHARD_FORMAT_VERSION,
        "inputs_hash": inputs_hash,
        "dtype": {
            "names": list(RAY_DTYPE.names),
            "formats": [
                RAY_DTYPE.fields[n][0].str
                if not RAY_DTYPE.fields[n][0].shape
                else [RAY_DTYPE.fields[n][0].base.str, list(RAY_DTYPE.fields[n][0].shape)]
                for n in RAY_DTYPE.names
            ],
            "offsets": [RAY_DTYPE.fields[n][1] for n in RAY_DTYPE.names],
            "itemsize": RAY_DTYPE.itemsize,
            "descr": str(RAY_DTYPE.descr),
        },  # fmt: skip
        "zone_labels": {ZONE_NAMES[z]: z for z in ZONES},
        "block_order": [ZONE_NAMES[z] for z in ZONES],
        "composition": {ZONE_NAMES[z]: c / 8 for z, c in zip(ZONES, COMPOSITION, strict=True)},
        "rays": rays,
        "rays_per_shard": int(max(r["rays"] for r in records)),
        "zone_counts": {ZONE_NAMES[z]: int(k) for z, k in zip(ZONES, kept, strict=True)},
        "sampled_zone_counts": {ZONE_NAMES[z]: int(k) for z, k in zip(ZONES, totals, strict=True)},
        "duplicated_rays": int(sum(m.get("duplicated", 0) for m in metas)),
        "missing_zone_rays": {n: int(sum(m["missing"][n] for m in metas)) for n in ZONE_NAMES.values()},
        "bytes": nbytes,
        "bytes_per_ray": nbytes / max(rays, 1),
        "normalization": bounds.to_dict(),
        "views": [str(v) for v in views],
        "cameras": cameras,
        "lights": light_table(calib, sorted({v.group for v in views})),
        "frames": int(sum(len(t.lights) for t in view_tasks)),
        "shards": records,
        "test": {"images": len(tests), "index": "test/index.json"},
        "config": {k: v for k, v in cfg_dict.items() if k != "force"},
        "coordinates": "world (metres); apply normalization to get the unit cube; rays from `cameras` and "
        "`lights` (lightstage.dataset.ray_table)",
    }
    write_json_atomic(manifest_path, manifest)
    shutil.rmtree(tmp_dir, ignore_errors=True)
    timings = {
        "sample_views_s": round(t_a, 3),
        "write_shards_s": round(t_b, 3),
        "test_images_s": round(t_c, 3),
    }
    return _summary(work, manifest, skipped=False, seconds=time.perf_counter() - t0, timings=timings)


def _intact(root: Path, record: dict[str, Any]) -> bool:
    """Whether a shard listed in the manifest is there with its recorded size (a rerun rebuilds otherwise)."""
    path = root / record["file"]
    return path.is_file() and path.stat().st_size == record.get("bytes")


def _summary(
    work: WorkDir, m: dict[str, Any], skipped: bool, seconds: float, timings: dict | None = None
) -> dict[str, Any]:
    summary = {
        "stage": "shard",
        "skipped": skipped,
        "rays": m["rays"],
        "shards": len(m["shards"]),
        "rays_per_shard": m["rays_per_shard"],
        "zone_counts": m["zone_counts"],
        "duplicated_rays": m["duplicated_rays"],
        "bytes": m["bytes"],
        "bytes_per_ray": m["bytes_per_ray"],
        "frames": m["frames"],
        "test_images": m["test"]["images"],
        "output": str(work.shards_dir / MANIFEST),
        "seconds": round(seconds, 3),
        "timings": timings or {},
        "warnings": [],
        "errors": [],
    }
    if any(m["missing_zone_rays"].values()):
        summary["warnings"].append(
            f"rays missing because a zone was empty in some views: {m['missing_zone_rays']}"
        )
    write_json_atomic(work.report("shard"), summary)
    return summary


# ---- reading ---------------------------------------------------------------------------------------------
def verify_shard(shards_dir: Path, record: dict[str, Any]) -> None:
    """Raise LightstageError naming the shard and the rebuild command if its size or sha256 differs from the
    manifest."""
    check_file(shards_dir, record)


def verify_shards(shards_dir: str | os.PathLike[str]) -> int:
    """Verify every shard and test image of a manifest (size and sha256); returns the number of shards."""
    m = load_manifest(shards_dir)
    for r in m["shards"]:
        verify_shard(Path(shards_dir), r)
    for r in read_test_index(shards_dir):
        check_file(shards_dir, r)
    return len(m["shards"])
