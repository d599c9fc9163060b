"""Structure from motion with pycolmap on the well-lit per-view images: one rig of N cameras, one frame per group.

The stage's cameras are rigidly mounted, so COLMAP models them as one rig (sensors = cameras, the first camera is
the reference sensor) seen in one frame per turntable group. The object is static in the world, the background
turns with the rig, so features are restricted to the (eroded) foreground mask. Intrinsics are known (stage.yaml
or `calibrate-intrinsics`, scaled to the processed resolution) and held fixed; the rig starts at its nominal
geometry and bundle adjustment refines it.

COLMAP uses the same pixel convention as lightstage: the centre of the first pixel is (0.5, 0.5) (SIFT keypoints
are shifted by +0.5 on extraction), so K at processed resolution is used as is.
"""

from __future__ import annotations

import os
import shutil
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from lightstage.calibration.sfm_mapping import (
    image_name,
    incremental,
    refine_from_initial,
    reprojection_errors,
)
from lightstage.errors import LightstageError
from lightstage.ids import ViewId


@dataclass(frozen=True)
class SfmOptions:
    """Knobs of the SfM run (defaults tuned on the simulator's `small` capture)."""

    max_features: int = 8192
    mask_erode_px: int = 2  # ignore features this close to the silhouette (it moves with the view)
    first_octave: int = -1  # -1 upsamples once: small processed images need it
    peak_threshold: float = 0.004
    max_ratio: float = 0.8
    ransac_max_error_px: float = 2.0
    refine_rig: bool = True
    min_num_matches: int = 15
    num_threads: int = 2
    seed: int = 0
    final_ba_iterations: int = 50
    use_rig: bool = True
    min_points_per_view: int = 15
    init: str = (
        "nominal"  # "nominal": triangulate from the nominal rig, then refine; "incremental": COLMAP mapper
    )
    refine_rounds: int = 3
    round_ba_iterations: int = 15  # bundle-adjustment iterations per triangulation round (the last: final_*)
    # COLMAP's own refinement inside each triangulation round (its defaults, 5 x 50, took half the mapping
    # time for no accuracy: the demo's poses agree to 0.001 deg); at least 1 (it completes and filters tracks).
    triangulation_ba_refinements: int = 1
    triangulation_ba_iterations: int = 10
    initial_max_reproj_px: float = 10.0  # triangulation/filter threshold of the first round (nominal poses)
    final_max_reproj_px: float = 2.0  # ... of the last round
    init_min_num_inliers: int = 30
    abs_pose_min_num_inliers: int = 15
    init_min_tri_angle_deg: float = 8.0
    domain_size_pooling: bool = False
    min_num_inliers: int = 12  # two-view verification
    # With initial poses, match only view pairs whose camera centres are within this angle seen from the world
    # origin, plus each view's `min_pair_neighbours` nearest (calibration.config); 0 or >= 180: exhaustive.
    max_pair_angle_deg: float = 90.0
    min_pair_neighbours: int = 8
    verbose: bool = False  # copy COLMAP's log to stderr after each run (it is always written to the log file)


@contextmanager
def native_stderr_to(log_path: Path, echo: bool = False) -> Iterator[Path]:
    """Redirect file descriptor 2 (C/C++ stderr: COLMAP's glog and Ceres lines, which bypass Python and
    `pycolmap.logging.minloglevel`) into `log_path` (appended) for the duration; fd 2 is restored on exit, also
    on error. With `echo` the captured text is copied to the real stderr afterwards. Python's own stderr goes
    to the file meanwhile too (it shares fd 2)."""
    log_path = Path(log_path)
    log_path.parent.mkdir(parents=True, exist_ok=True)
    sys.stderr.flush()
    saved = os.dup(2)
    try:
        with open(log_path, "ab") as f:
            start = f.tell()
            os.dup2(f.fileno(), 2)
            try:
                yield log_path
            finally:
                sys.stderr.flush()
                os.dup2(saved, 2)
    finally:
        os.close(saved)
    if echo:
        with open(log_path, "rb") as f:
            f.seek(start)
            sys.stderr.write(f.read().decode("utf-8", "replace"))
            sys.stderr.flush()


@dataclass
class SfmResult:
    """What registration needs from SfM, plus statistics for the report."""

    sensor_from_rig: dict[str, tuple[np.ndarray, np.ndarray]]  # camera id -> (R, t), SfM units
    rig_from_world: dict[str, tuple[np.ndarray, np.ndarray]]  # group -> (R, t), SfM units
    registered: list[ViewId]
    unregistered: list[ViewId]
    stats: dict = field(default_factory=dict)
    reconstruction: object = None  # pycolmap.Reconstruction


def view_pairs(
    poses: dict[ViewId, tuple[np.ndarray, np.ndarray]],
    views: list[ViewId],
    max_angle_deg: float,
    min_neighbours: int = 0,
) -> list[tuple[ViewId, ViewId]]:
    """Pairs of views whose camera centres (from `poses`, world-to-camera) are within `max_angle_deg` of each
    other as seen from the world origin (the object): the pairs worth matching on a turntable stage. Each view
    also keeps its `min_neighbours` nearest views by that angle, however far, so a sparse stage (few cameras, one
    group) still gets a connected pair graph."""
    centres = np.stack([-np.asarray(poses[v][0]).T @ np.asarray(poses[v][1]) for v in views])
    dirs = centres / np.linalg.norm(centres, axis=1, keepdims=True)
    cos = dirs @ dirs.T
    keep = cos >= np.cos(np.deg2rad(max_angle_deg))
    k = min(min_neighbours, len(views) - 1)
    if k > 0:
        np.fill_diagonal(cos, -np.inf)
        nearest = np.argsort(-cos, axis=1, kind="stable")[:, :k]
        rows = np.repeat(np.arange(len(views)), k)
        keep[rows, nearest.ravel()] = keep[nearest.ravel(), rows] = True
    i, j = np.nonzero(np.triu(keep, 1))
    return [(views[a], views[b]) for a, b in zip(i.tolist(), j.tolist(), strict=True)]


def prepare_images(
    views: dict[ViewId, tuple[Path, Path]], image_dir: Path, mask_dir: Path, erode_px: int
) -> list[str]:
    """Copy well-lit images into the COLMAP layout `<camera>/<group>.png` and write eroded feature masks."""
    names = []
    kernel = (
        cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * erode_px + 1, 2 * erode_px + 1))
        if erode_px
        else None
    )
    for view, (wellit, mask) in sorted(views.items()):
        name = image_name(view)
        img = cv2.imread(str(wellit), cv2.IMREAD_UNCHANGED)
        if img is None:
            raise LightstageError(f"{wellit}: cannot read the well-lit image of view {view}")
        m = cv2.imread(str(mask), cv2.IMREAD_GRAYSCALE)
        if m is None:
            raise LightstageError(f"{mask}: cannot read the mask of view {view}")
        if m.shape != img.shape[:2]:
            raise LightstageError(f"{mask}: mask size {m.shape[::-1]} differs from image {img.shape[1::-1]}")
        m = np.where(m > 127, 255, 0).astype(np.uint8)
        if kernel is not None:
            m = cv2.erode(m, kernel)
        (image_dir / view.camera).mkdir(parents=True, exist_ok=True)
        (mask_dir / view.camera).mkdir(parents=True, exist_ok=True)
        shutil.copyfile(wellit, image_dir / name)
        # COLMAP reads the mask of image NAME from MASK_DIR/NAME.png; features where the mask is 0 are dropped.
        cv2.imwrite(str(mask_dir / (name + ".png")), m)
        names.append(name)
    return names


def run_sfm(
    views: dict[ViewId, tuple[Path, Path]],
    intrinsics: dict[str, tuple[np.ndarray, np.ndarray, int, int]],
    camera_order: list[str],
    work_dir: Path,
    options: SfmOptions = SfmOptions(),
    log=print,
    initial_poses: dict[ViewId, tuple[np.ndarray, np.ndarray]] | None = None,
    log_path: Path | None = None,
) -> SfmResult:
    """Run feature extraction, exhaustive matching and rig-aware incremental mapping.

    `views`: view -> (well-lit PNG, mask PNG). `intrinsics`: camera id -> (K, dist, width, height) at the
    images' resolution. `initial_poses` (view -> world-to-camera (R, t), e.g. the nominal stage): when given
    and `options.init == "nominal"`, mapping starts from them (rig-structured triangulation + bundle adjustment
    rounds) instead of COLMAP's incremental registration, which needs more matches than small objects give.
    COLMAP's own log (C-level stderr) goes to `log_path` (default: `work_dir`/../colmap.log), echoed to stderr
    when `options.verbose`. Raises LightstageError naming the views that could not be registered.
    """

    import pycolmap

    pycolmap.set_random_seed(options.seed)
    # COLMAP logs every matching block, triangulation step and solver retry through glog (~1,000 lines per run,
    # thousands in the demo), from C++ threads that `pycolmap.logging.minloglevel` does not silence: its stderr
    # goes to the log file (fresh per run) and is shown only when verbose.
    log_path = Path(log_path) if log_path is not None else Path(work_dir).parent / "colmap.log"
    log_path.parent.mkdir(parents=True, exist_ok=True)
    log_path.write_bytes(b"")
    try:
        with native_stderr_to(log_path, echo=options.verbose):
            return _run_sfm(views, intrinsics, camera_order, work_dir, options, log, initial_poses)
    except LightstageError:
        log(f"COLMAP's log: {log_path}")
        raise


def _run_sfm(
    views: dict[ViewId, tuple[Path, Path]],
    intrinsics: dict[str, tuple[np.ndarray, np.ndarray, int, int]],
    camera_order: list[str],
    work_dir: Path,
    options: SfmOptions,
    log,
    initial_poses: dict[ViewId, tuple[np.ndarray, np.ndarray]] | None,
) -> SfmResult:
    """The body of `run_sfm` (COLMAP's stderr already redirected)."""
    import time

    import pycolmap

    t0 = time.perf_counter()
    if work_dir.exists():
        shutil.rmtree(work_dir)
    image_dir, mask_dir = work_dir / "images", work_dir / "masks"
    db_path = work_dir / "database.db"
    image_dir.mkdir(parents=True)
    mask_dir.mkdir(parents=True)
    names = prepare_images(views, image_dir, mask_dir, options.mask_erode_px)
    by_name = {image_name(v): v for v in views}
    cams_present = [c for c in camera_order if any(v.camera == c for v in views)]
    if not cams_present:
        raise LightstageError("SfM: no views to calibrate")

    has_dist = any(np.any(np.asarray(intrinsics[c][1]) != 0) for c in cams_present)
    model = "OPENCV" if has_dist else "PINHOLE"
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = model
    reader.mask_path = str(mask_dir)
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.num_threads = options.num_threads
    extraction.sift.max_num_features = options.max_features
    extraction.sift.first_octave = options.first_octave
    extraction.sift.peak_threshold = options.peak_threshold
    extraction.sift.domain_size_pooling = options.domain_size_pooling
    pycolmap.extract_features(
        db_path,
        image_dir,
        image_names=names,
        camera_mode=pycolmap.CameraMode.PER_FOLDER,
        reader_options=reader,
        extraction_options=extraction,
        device=pycolmap.Device.cpu,
    )
    t_extract = time.perf_counter() - t0

    # Known intrinsics per camera.
    with pycolmap.Database.open(db_path) as db:
        camera_of = {}
        for image in db.read_all_images():
            camera_of[by_name[image.name].camera] = image.camera_id
        num_keypoints = {
            image.name: db.num_keypoints_for_image(image.image_id) for image in db.read_all_images()
        }
        for cid in cams_present:
            K, dist, w, h = intrinsics[cid]
            cam = db.read_camera(camera_of[cid])
            if cam.width != w or cam.height != h:
                raise LightstageError(
                    f"SfM: images of camera {cid} are {cam.width}x{cam.height}, expected {w}x{h}"
                )
            params = [K[0, 0], K[1, 1], K[0, 2], K[1, 2]]
            if model == "OPENCV":
                d = np.zeros(5) if dist is None else np.asarray(dist, dtype=np.float64)
                params += [d[0], d[1], d[2], d[3]]
                if abs(d[4]) > 0:
                    raise LightstageError(
                        f"SfM: camera {cid} has k3 distortion, which COLMAP's OPENCV model lacks"
                    )
            cam.params = params
            cam.has_prior_focal_length = True
            db.update_camera(cam)

    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = options.num_threads
    matching.sift.max_ratio = options.max_ratio
    verification = pycolmap.TwoViewGeometryOptions()
    verification.ransac.max_error = options.ransac_max_error_px
    verification.detect_watermark = False
    verification.min_num_inliers = options.min_num_inliers
    # COLMAP seeds each pair's RANSAC from the clock unless told: with a seed, verification gives the same inliers
    # whichever thread takes the pair (6,433 of 6,435 demo pairs identical across runs against 5,283 unseeded)
    verification.ransac.random_seed = options.seed
    pairs = None
    if initial_poses is not None and 0 < options.max_pair_angle_deg < 180:
        pairs = view_pairs(
            initial_poses, sorted(views), options.max_pair_angle_deg, options.min_pair_neighbours
        )
    if pairs is None:
        pycolmap.match_exhaustive(
            db_path, matching_options=matching, verification_options=verification, device=pycolmap.Device.cpu
        )
    else:
        pair_file = work_dir / "pairs.txt"
        pair_file.write_text("".join(f"{image_name(a)} {image_name(b)}\n" for a, b in pairs))
        pairing = pycolmap.ImportedPairingOptions()
        pairing.match_list_path = str(pair_file)
        pycolmap.match_image_pairs(
            db_path,
            matching_options=matching,
            pairing_options=pairing,
            verification_options=verification,
            device=pycolmap.Device.cpu,
        )
    t_match = time.perf_counter() - t0 - t_extract

    mapping = pycolmap.IncrementalPipelineOptions()
    mapping.num_threads = options.num_threads
    mapping.random_seed = options.seed
    mapping.min_num_matches = options.min_num_matches
    mapping.ba_refine_focal_length = False
    mapping.ba_refine_principal_point = False
    mapping.ba_refine_extra_params = False
    mapping.ba_refine_sensor_from_rig = options.refine_rig
    mapping.mapper.abs_pose_refine_focal_length = False
    mapping.mapper.abs_pose_refine_extra_params = False
    mapping.multiple_models = False
    mapping.mapper.init_min_num_inliers = options.init_min_num_inliers
    mapping.mapper.abs_pose_min_num_inliers = options.abs_pose_min_num_inliers
    mapping.mapper.init_min_tri_angle = options.init_min_tri_angle_deg
    sparse_dir = work_dir / "sparse"
    sparse_dir.mkdir()
    if options.init == "nominal" and initial_poses is not None:
        rec = refine_from_initial(
            db_path, image_dir, sparse_dir, views, initial_poses, cams_present, camera_of, mapping, options
        )
        recs = {0: rec}
        t_map = time.perf_counter() - t0 - t_extract - t_match
        t_ba = 0.0
    else:
        rec, recs, t_map, t_ba = incremental(
            db_path, image_dir, sparse_dir, views, cams_present, mapping, options, t0 + t_extract + t_match
        )

    registered, observed, sensor_from_rig, rig_from_world = [], [], {}, {}
    for image in rec.images.values():
        # A view is *observed* when enough triangulated points constrain it (with the nominal initialisation
        # every image has a pose from the start, so has_pose alone means nothing).
        if image.has_pose and image.num_points3D >= options.min_points_per_view:
            observed.append(by_name[image.name])
    # Under the rig model a view's pose is its camera's rig pose composed with its group's frame pose: it is
    # registered when its camera is observed in some group and its group is observed by >= 3 cameras.
    obs_cams = {v.camera for v in observed}
    obs_groups = {g for g in {v.group for v in observed} if sum(v.group == g for v in observed) >= 3}
    for image in rec.images.values():
        v = by_name[image.name]
        if image.has_pose and (
            v in set(observed) or (options.use_rig and v.camera in obs_cams and v.group in obs_groups)
        ):
            registered.append(v)
    reg_set = set(registered)
    unregistered = sorted(v for v in views if v not in reg_set)
    for rig in rec.rigs.values():
        for sensor_id in rig.sensor_ids():
            cam_id = sensor_id.id
            cid = next((c for c, i in camera_of.items() if i == cam_id), None)
            if cid is None:
                continue
            if rig.is_ref_sensor(sensor_id):
                sensor_from_rig[cid] = (np.eye(3), np.zeros(3))
            else:
                T = rig.sensor_from_rig(sensor_id)
                sensor_from_rig[cid] = (T.rotation.matrix(), np.asarray(T.translation))
    groups_of_frame: dict[int, set[str]] = {}
    for image in rec.images.values():
        groups_of_frame.setdefault(image.frame_id, set()).add(by_name[image.name].group)
    for frame_id, frame in rec.frames.items():
        if not frame.has_pose:
            continue
        groups = groups_of_frame.get(frame_id, set())
        if len(groups) != 1:
            raise LightstageError(f"SfM: a COLMAP frame holds groups {sorted(groups)} (image naming broke)")
        T = frame.rig_from_world
        rig_from_world[groups.pop()] = (T.rotation.matrix(), np.asarray(T.translation))

    errors = reprojection_errors(rec)
    track_lengths = np.array([p.track.length() for p in rec.points3D.values()]) if rec.num_points3D() else []
    stats = {
        "num_views": len(views),
        "num_pairs_matched": len(pairs) if pairs is not None else len(views) * (len(views) - 1) // 2,
        "num_registered": len(registered),
        "num_observed": len(observed),
        "min_points_per_view": options.min_points_per_view,
        "unregistered": [str(v) for v in unregistered],
        "num_points3D": int(rec.num_points3D()),
        "num_observations": int(rec.compute_num_observations()),
        "mean_track_length": float(np.mean(track_lengths)) if len(track_lengths) else 0.0,
        "reprojection_error_px": {
            "mean": float(errors.mean()) if errors.size else None,
            "median": float(np.median(errors)) if errors.size else None,
            "p95": float(np.percentile(errors, 95)) if errors.size else None,
        },
        "keypoints_per_image": {
            "mean": float(np.mean(list(num_keypoints.values()))),
            "min": int(min(num_keypoints.values())),
        },
        "num_reconstructions": len(recs),
        "seconds": {
            "extract": round(t_extract, 2),
            "match": round(t_match, 2),
            "map": round(t_map, 2),
            "final_ba": round(t_ba, 2),
        },
    }
    log(
        f"SfM: {len(registered)}/{len(views)} views registered, {rec.num_points3D()} points, "
        f"mean reprojection error {errors.mean() if errors.size else float('nan'):.3f} px, "
        f"mean track length {stats['mean_track_length']:.2f}"
    )
    return SfmResult(sensor_from_rig, rig_from_world, sorted(registered), unregistered, stats, rec)
