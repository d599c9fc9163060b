"""Scene bounds from the per-view masks and calibrated cameras: a conservative visual hull (space carving)
on a voxel grid, coarse then fine, giving the box and the normalisation x_norm = (x_world - centre) / scale
that maps it inside the model's unit cube [-1, 1]^3 with a margin. No per-object tables."""

from __future__ import annotations

import json
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from lightstage.atomic import write_json_atomic
from lightstage.config import load, require
from lightstage.errors import LightstageError
from lightstage.executor import Executor
from lightstage.ids import ViewId
from lightstage.records.processed import read_mask
from lightstage.workdir import WorkDir

BOUNDS_FORMAT_VERSION = 1


@dataclass(frozen=True)
class BoundsConfig:
    """Voxels per axis per pass, passes (each refines the previous box), the consistency a voxel needs (fraction
    of the views that see it inside their image whose mask covers it), the least views (count, and fraction of
    all views) that must see it inside their image, and the margin of the unit-cube normalisation around the box.
    A view judges only voxels that project inside its frame: what lies outside every frame (the stand below the
    bottom edge of each view) is never observed and is carved."""

    resolution: int = 64
    passes: int = 2
    consistency: float = 0.9
    min_views: int = 2
    min_seen: float = 0.0
    margin: float = 0.1
    force: bool = False

    def __post_init__(self) -> None:
        require(self.resolution >= 8, "resolution", f"must be >= 8, got {self.resolution}")
        require(self.passes >= 1, "passes", f"must be >= 1, got {self.passes}")
        require(0 < self.consistency <= 1, "consistency", f"must be in (0, 1], got {self.consistency}")
        require(self.min_views >= 1, "min_views", f"must be >= 1, got {self.min_views}")
        require(self.margin >= 0, "margin", f"must be >= 0, got {self.margin}")

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> BoundsConfig:
        """The strict loader (`lightstage.config`): unknown keys, wrong types and bad values name the key."""
        return load(cls, d)


@dataclass(frozen=True)
class Bounds:
    """The object's axis-aligned box (world, metres), the unit-cube normalisation, and the carved visual hull
    (n, n, n) bool voxels spanning the box (None when not stored), a prior for the model's occupancy grid."""

    box_min: np.ndarray
    box_max: np.ndarray
    centre: np.ndarray
    scale: float
    hull: np.ndarray | None = None

    def normalize(self, x: np.ndarray) -> np.ndarray:
        return (np.asarray(x) - self.centre) / self.scale

    def to_dict(self) -> dict[str, Any]:
        d = {
            "format_version": BOUNDS_FORMAT_VERSION,
            "centre": [float(x) for x in self.centre],
            "scale": float(self.scale),
            "box_min": [float(x) for x in self.box_min],
            "box_max": [float(x) for x in self.box_max],
            "convention": "x_norm = (x_world - centre) / scale; the box lies inside [-1, 1]^3 with the margin",
        }
        if self.hull is not None:
            d["hull"] = encode_hull(self.hull)
        return d


def encode_hull(hull: np.ndarray) -> dict[str, Any]:
    """JSON form of a bool voxel grid over the box: its shape and np.packbits of the C-order voxels, base64."""
    import base64

    bits = base64.b64encode(np.packbits(hull.astype(bool).ravel()).tobytes()).decode("ascii")
    return {
        "shape": list(hull.shape),
        "order": "x, y, z index (C order); voxels tile box_min..box_max",
        "bits": bits,
    }


def decode_hull(d: dict[str, Any]) -> np.ndarray:
    """The bool voxel grid of `encode_hull`."""
    import base64

    shape = tuple(int(n) for n in d["shape"])
    raw = np.frombuffer(base64.b64decode(d["bits"]), np.uint8)
    return np.unpackbits(raw)[: int(np.prod(shape))].reshape(shape).astype(bool)


def load_bounds(path: str | Path) -> Bounds:
    """Read bounds.json."""
    path = Path(path)
    try:
        d = json.loads(path.read_text())
        hull = decode_hull(d["hull"]) if "hull" in d else None
        return Bounds(
            np.array(d["box_min"]), np.array(d["box_max"]), np.array(d["centre"]), float(d["scale"]), hull
        )
    except OSError as e:
        raise LightstageError(f"{path}: cannot read bounds ({e.strerror}); run `lightstage bounds`") from None
    except (KeyError, TypeError, ValueError) as e:
        raise LightstageError(f"{path}: malformed bounds ({type(e).__name__}: {e})") from None


@dataclass
class _View:
    K: np.ndarray
    R: np.ndarray
    t: np.ndarray
    dist_to_fg: np.ndarray  # distance (px) from each pixel to the nearest mask pixel


def carve(views: list[_View], lo: np.ndarray, hi: np.ndarray, cfg: BoundsConfig) -> np.ndarray:
    """Boolean occupancy (n, n, n) of voxel centres in [lo, hi]. A view votes on a voxel in front of it:
    - projected inside the image: consistent when its footprint (a disc of the voxel's half-diagonal) touches
      the mask;
    - projected outside: inconsistent when the mask does not reach that border (nearest border pixel), else
      it abstains (the object may continue out of frame there, but this view never saw it).
    Kept: at least `need` views see the voxel inside their image and `consistency` of the votes agree. So the
    stand below the bottom edge of every frame, seen by no view, is carved."""
    n = cfg.resolution
    step = (hi - lo) / n
    axes = [lo[i] + (np.arange(n) + 0.5) * step[i] for i in range(3)]
    X = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3).astype(np.float32)
    radius = 0.5 * float(np.linalg.norm(step))
    inside_views = np.zeros(len(X), np.int32)
    votes = np.zeros(len(X), np.int32)
    hits = np.zeros(len(X), np.int32)
    for v in views:
        xc = X @ v.R.T.astype(np.float32) + v.t.astype(np.float32)
        z = xc[:, 2]
        front = z > 1e-6
        uv = (xc[:, :2] / np.where(front, z, 1.0)[:, None]) * np.diag(v.K)[:2] + v.K[:2, 2]
        h, w = v.dist_to_fg.shape
        idx = np.flatnonzero(front)
        u_, v_ = uv[idx, 0], uv[idx, 1]
        inside = (u_ >= 0) & (u_ < w) & (v_ >= 0) & (v_ < h)
        d = v.dist_to_fg[np.clip(v_, 0, h - 1).astype(int), np.clip(u_, 0, w - 1).astype(int)]
        near_mask = d <= v.K[0, 0] * radius / z[idx] + 0.75
        counts = inside | ~near_mask  # outside the frame next to the mask: abstain
        inside_views[idx] += inside
        votes[idx] += counts
        hits[idx] += inside & near_mask
    need = max(cfg.min_views, int(np.ceil(cfg.min_seen * len(views) - 1e-9)))
    keep = (inside_views >= need) & (hits >= np.ceil(cfg.consistency * votes - 1e-9))
    return keep.reshape(n, n, n)


def estimate_bounds(views: list[_View], cfg: BoundsConfig) -> tuple[Bounds, dict[str, Any]]:
    """Coarse-to-fine carving from a cube around the point nearest to all optical axes."""
    centres = np.stack([-v.R.T @ v.t for v in views])
    axes = np.stack([v.R[2] for v in views])
    A = np.zeros((3, 3))
    b = np.zeros(3)
    for c, a in zip(centres, axes, strict=True):
        P = np.eye(3) - np.outer(a, a)
        A += P
        b += P @ c
    c0 = np.linalg.lstsq(A, b, rcond=None)[0]
    half = 0.5 * float(np.min(np.linalg.norm(centres - c0, axis=1)))
    lo, hi = c0 - half, c0 + half
    info: dict[str, Any] = {"initial_box": [lo.tolist(), hi.tolist()], "passes": []}
    for p in range(cfg.passes):
        occ = carve(views, lo, hi, cfg)
        if not occ.any():
            raise LightstageError(
                "visual hull is empty: the masks and the calibrated cameras do not agree on any region "
                f"(pass {p + 1}, box {np.round(lo, 3).tolist()}..{np.round(hi, 3).tolist()})"
            )
        step = (hi - lo) / cfg.resolution
        idx = np.argwhere(occ)
        new_lo = lo + idx.min(0) * step
        new_hi = lo + (idx.max(0) + 1) * step
        info["passes"].append(
            {
                "box": [new_lo.tolist(), new_hi.tolist()],
                "voxel_size": step.tolist(),
                "occupied": int(occ.sum()),
            }
        )
        if p + 1 < cfg.passes:  # refine on the box grown by one voxel (the carving is conservative)
            lo, hi = new_lo - step, new_hi + step
        else:
            lo, hi = new_lo, new_hi
            lo_i, hi_i = idx.min(0), idx.max(0) + 1
            hull = occ[lo_i[0] : hi_i[0], lo_i[1] : hi_i[1], lo_i[2] : hi_i[2]]
    centre = 0.5 * (lo + hi)
    scale = float(np.max(0.5 * (hi - lo))) * (1.0 + cfg.margin)
    return Bounds(lo, hi, centre, scale, hull), info


def write_bounds_picture(path: Path, work: WorkDir, calib: Any, views: list[ViewId], bounds: Bounds) -> None:
    """PNG: the box's 12 edges projected onto up to 4 views (well-lit image if present, else the mask), tiled."""
    import cv2

    from lightstage.frames import write_image

    lo, hi = bounds.box_min, bounds.box_max
    corners = np.array(
        [[(lo, hi)[i][0], (lo, hi)[j][1], (lo, hi)[k][2]] for i in (0, 1) for j in (0, 1) for k in (0, 1)]
    )
    edges = [(a, b) for a in range(8) for b in range(a + 1, 8) if bin(a ^ b).count("1") == 1]
    tiles = []
    for v in views:
        cam = calib.views[v].camera()
        if work.wellit(v).is_file():
            img = cv2.imread(str(work.wellit(v)), cv2.IMREAD_COLOR)
        else:
            img = None
        if img is None or img.shape[:2] != (cam.height, cam.width):
            img = np.repeat(read_mask(work.mask(v)).astype(np.uint8)[..., None] * 255, 3, axis=2)
        scale = max(1, 512 // max(cam.width, cam.height))
        img = cv2.resize(img, (cam.width * scale, cam.height * scale), interpolation=cv2.INTER_NEAREST)
        xc = corners @ cam.R.T + cam.t
        if np.any(xc[:, 2] <= 0):
            continue
        uv = (xc[:, :2] / xc[:, 2:]) * np.diag(cam.K)[:2] + cam.K[:2, 2]
        for a, b in edges:
            p0 = tuple(int(round(x)) for x in uv[a] * scale)
            p1 = tuple(int(round(x)) for x in uv[b] * scale)
            cv2.line(img, p0, p1, (0, 200, 255), 1, cv2.LINE_AA)
        tiles.append(img[..., ::-1])  # BGR -> RGB
    if tiles:
        h = max(t.shape[0] for t in tiles)
        tiles = [np.pad(t, ((0, h - t.shape[0]), (0, 0), (0, 0))) for t in tiles]
        write_image(path, np.ascontiguousarray(np.concatenate(tiles, axis=1)))


def _inputs_key(work: WorkDir, views: list[ViewId], config: BoundsConfig) -> str:
    """Fingerprint of what the bounds depend on: calibration, the views, their masks (size, mtime), config."""
    import hashlib

    h = hashlib.sha256(work.calibration.read_bytes())
    cfg = {k: v for k, v in asdict(config).items() if k != "force"}
    h.update(json.dumps(cfg, sort_keys=True).encode())
    for v in views:
        p = work.mask(v)
        st = p.stat() if p.is_file() else None
        h.update(f"{v}:{st.st_size if st else -1}:{st.st_mtime_ns if st else -1};".encode())
    return h.hexdigest()[:16]


def _training_views(work: WorkDir, calib_views: list[ViewId]) -> list[ViewId]:
    if work.split.is_file():
        from lightstage.records.split import load_split

        wanted = set(load_split(work.split).train.views())
        return [v for v in calib_views if v in wanted]
    return calib_views


def run_bounds(
    work: WorkDir, config: BoundsConfig, executor: Executor | None = None, progress: bool = True
) -> dict[str, Any]:
    """The bounds stage: carve the visual hull of the training views' masks; write WORK/bounds.json (and
    bounds.png) and reports/bounds.json. One process (`executor` is unused); skipped when bounds.json was made
    from the same calibration, masks and config (`force` redoes it)."""
    import cv2

    from lightstage.records.calibration import Calibration

    t0 = time.perf_counter()
    calib = Calibration.load(work.calibration)
    names = _training_views(work, sorted(calib.views))
    key = _inputs_key(work, names, config)
    if work.bounds.is_file() and not config.force:
        d = json.loads(work.bounds.read_text())
        if d.get("inputs_key") == key:
            b = load_bounds(work.bounds)
            return {
                "stage": "bounds",
                "skipped": True,
                "centre": b.centre.tolist(),
                "scale": b.scale,
                "views": d.get("views", 0),
                "occupied_voxels": d.get("occupied_voxels", 0),
                "output": str(work.bounds),
            }
    views = []
    missing = []
    for v in names:
        path = work.mask(v)
        if not path.is_file():
            missing.append(str(v))
            continue
        cam = calib.views[v].camera()
        mask = read_mask(path)
        if mask.shape != (cam.height, cam.width):
            raise LightstageError(
                f"{path}: mask is {mask.shape[1]}x{mask.shape[0]}, camera is {cam.width}x{cam.height}"
            )
        dist = cv2.distanceTransform((~mask).astype(np.uint8), cv2.DIST_L2, 5)
        views.append(_View(cam.K, cam.R, cam.t, dist))
    if len(views) < config.min_views:
        if missing:
            raise LightstageError(
                f"{work.root}: {len(views)} of {len(names)} view masks found (missing e.g. {missing[:2]}); "
                "run `lightstage preprocess` first"
            )
        raise LightstageError(
            f"{work.root}: {len(views)} training view(s); carving the scene bounds needs at least {config.min_views}"
        )
    bounds, info = estimate_bounds(views, config)
    record = bounds.to_dict() | {
        "method": "visual hull (conservative space carving)",
        "views": len(views),
        "occupied_voxels": info["passes"][-1]["occupied"],
        "margin": config.margin,
        "carving": info,
        "config": asdict(config),
        "inputs_key": key,
    }
    write_json_atomic(work.bounds, record)
    picture = work.root / "bounds.png"
    write_bounds_picture(picture, work, calib, names[:4], bounds)
    summary = {
        "stage": "bounds",
        "skipped": False,
        "centre": bounds.centre.tolist(),
        "scale": bounds.scale,
        "views": len(views),
        "missing_masks": len(missing),
        "occupied_voxels": record["occupied_voxels"],
        "output": str(work.bounds),
        "picture": str(picture),
        "seconds": round(time.perf_counter() - t0, 3),
        "warnings": [f"{len(missing)} view masks missing"] if missing else [],
        "errors": [],
    }
    write_json_atomic(work.report("bounds"), summary)
    return summary
