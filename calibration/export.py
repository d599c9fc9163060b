"""Exports of a calibration for other tools: a COLMAP sparse model and a nerfstudio-style transforms.json.

Both are in the world frame of the conventions (metres) at the processed resolution (raw / 4).

COLMAP (`WORK/calibration/colmap/`): one camera per stage camera, one rig of the real sensors (first camera =
reference sensor) with one frame per turntable group when the calibration is rigid (it is for every method:
the stage's cameras are fixed and the rig turns as a whole), the images it names written beside it
(`images/<camera>/<group>.png`: the view's tonemapped well-lit image at the model's resolution, hard-linked when
the file system allows) with COLMAP-style feature masks (`masks/<camera>/<group>.png.png`), and — for the sfm
method — the SfM points with their 2D observations and tracks (observations that reproject more than
`max_reproj_px` under the exported cameras are left out). The nominal method has cameras only.

nerfstudio (`WORK/calibration/transforms.json`): OpenGL camera-to-world (`lightstage.cameras.opencv_to_opengl_c2w`),
per-frame intrinsics and distortion, `mask_path`, `applied_transform` (identity: the world frame is ours) and,
when WORK/split.json exists, `train_filenames` / `val_filenames` / `test_filenames` from the split's views.
"""

from __future__ import annotations

import os
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from lightstage.atomic import write_json_atomic
from lightstage.cameras import opencv_to_opengl_c2w
from lightstage.errors import LightstageError
from lightstage.ids import ViewId
from lightstage.records.calibration import Calibration
from lightstage.workdir import DOWNSCALE, WorkDir

RIGID_TOL = 1e-6  # rad / m: sensor-from-rig poses that differ by less are one rig


def colmap_image_name(group: str, camera: str) -> str:
    """Image name of a view inside the exported COLMAP model."""
    return f"{camera}/{group}.png"


@dataclass(frozen=True)
class SfmTracks:
    """SfM points in the world frame with their observations at the processed resolution."""

    xyz: np.ndarray  # (P, 3) world positions, metres
    colors: np.ndarray  # (P, 3) uint8
    observations: list[list[tuple[str, float, float]]]  # per point: (image name, x, y) in processed pixels


def sfm_tracks(rec: Any, world_from_sfm: Any, pixel_scale: float) -> SfmTracks:
    """The points and tracks of a pycolmap reconstruction mapped to the world (`world_from_sfm.apply`) and
    to processed pixels (`pixel_scale` = SfM factor / DOWNSCALE; both pixel grids put the first pixel centre
    at 0.5, so coordinates scale as they are)."""
    ids = sorted(rec.points3D)
    xyz = np.stack([rec.points3D[i].xyz for i in ids]) if ids else np.zeros((0, 3))
    colors = np.stack([rec.points3D[i].color for i in ids]) if ids else np.zeros((0, 3), np.uint8)
    observations = []
    for i in ids:
        obs = []
        for el in rec.points3D[i].track.elements:
            image = rec.images[el.image_id]
            x, y = np.asarray(image.points2D[el.point2D_idx].xy, float) * pixel_scale
            obs.append((image.name, float(x), float(y)))
        observations.append(obs)
    world = np.asarray(world_from_sfm.apply(xyz), float) if len(xyz) else xyz
    return SfmTracks(world, np.asarray(colors, np.uint8), observations)


# ---- the rig ------------------------------------------------------------------------------------------
def _compose(a: tuple[np.ndarray, np.ndarray], b: tuple[np.ndarray, np.ndarray]) -> tuple:
    """(R, t) of x -> a(b(x))."""
    return a[0] @ b[0], a[0] @ b[1] + a[1]


def _inverse(a: tuple[np.ndarray, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    return a[0].T, -a[0].T @ a[1]


def rig_structure(calib: Calibration) -> tuple[dict[str, tuple], dict[str, tuple]] | None:
    """(sensor_from_rig per camera, rig_from_world per group) with the first camera as reference sensor, or
    None when the views are not one rigid rig (a camera never seen with the reference, or relative poses that
    differ between groups by more than RIGID_TOL)."""
    pose = {v: (np.asarray(c.R, float), np.asarray(c.t, float)) for v, c in calib.views.items()}
    cameras = sorted({v.camera for v in pose})
    groups = sorted({v.group for v in pose})
    ref = cameras[0]
    sensor: dict[str, tuple] = {ref: (np.eye(3), np.zeros(3))}
    for c in cameras[1:]:
        rel = [
            _compose(pose[ViewId(g, c)], _inverse(pose[ViewId(g, ref)]))
            for g in groups
            if ViewId(g, c) in pose and ViewId(g, ref) in pose
        ]
        if not rel:
            return None
        for R, t in rel[1:]:
            dR = np.linalg.norm(R - rel[0][0])
            if dR > RIGID_TOL or np.linalg.norm(t - rel[0][1]) > RIGID_TOL:
                return None
        sensor[c] = rel[0]
    frames = {}
    for g in groups:
        c = ref if ViewId(g, ref) in pose else next(c for c in cameras if ViewId(g, c) in pose)
        frames[g] = _compose(_inverse(sensor[c]), pose[ViewId(g, c)])
    return sensor, frames


# ---- the COLMAP model ----------------------------------------------------------------------------------
def _camera(camera_id: int, vc: Any) -> Any:
    """The COLMAP camera of a view at the processed resolution (PINHOLE, or OPENCV with distortion)."""
    import pycolmap

    pin = vc.camera(DOWNSCALE)
    K, d = pin.K, np.asarray(pin.dist, dtype=np.float64)
    has_dist = bool(np.any(d != 0))
    if abs(d[4]) > 0:
        raise LightstageError(f"camera {camera_id}: k3 distortion has no COLMAP OPENCV equivalent")
    cam = pycolmap.Camera.create_from_model_name(
        camera_id, "OPENCV" if has_dist else "PINHOLE", float(K[0, 0]), pin.width, pin.height
    )
    params = [K[0, 0], K[1, 1], K[0, 2], K[1, 2]]
    if has_dist:
        params += [d[0], d[1], d[2], d[3]]
    cam.params = params
    return cam


def _rigid(pose: tuple[np.ndarray, np.ndarray]) -> Any:
    import pycolmap

    return pycolmap.Rigid3d(pycolmap.Rotation3d(np.asarray(pose[0], float)), np.asarray(pose[1], float))


def _kept_observations(
    calib: Calibration, tracks: SfmTracks | None, max_reproj_px: float
) -> tuple[list[list[tuple[str, float, float]]], dict[str, Any]]:
    """Per point, the observations that reproject within `max_reproj_px` under the calibration's cameras;
    points left with fewer than two are dropped (empty list)."""
    if tracks is None:
        none = "none: cameras only (no SfM points: the nominal method matches no features)"
        return [], {"points": 0, "observations": 0, "dropped_observations": 0, "max_reprojection_px": None,
                    "tracks": none}  # fmt: skip
    cams = {
        colmap_image_name(v.group, v.camera): (
            _camera(1, vc),
            np.asarray(vc.R, float),
            np.asarray(vc.t, float),
        )
        for v, vc in calib.views.items()
    }
    kept, dropped, worst = [], 0, 0.0
    for X, obs in zip(tracks.xyz, tracks.observations, strict=True):
        good = []
        for name, x, y in obs:
            if name not in cams:
                dropped += 1
                continue
            cam, R, t = cams[name]
            proj = np.asarray(cam.img_from_cam((R @ np.asarray(X, float) + t)[None]), float).reshape(2)
            err = float(np.hypot(*(proj - (x, y))))
            if err <= max_reproj_px:
                good.append((name, x, y))
                worst = max(worst, err)
            else:
                dropped += 1
        if len(good) < 2:
            dropped += len(good)
            good = []
        kept.append(good)
    n_obs = sum(len(k) for k in kept)
    stats = {
        "points": sum(1 for k in kept if k),
        "observations": n_obs,
        "dropped_observations": dropped,
        "max_reprojection_px": worst if n_obs else None,
        "tracks": f"SfM points with observations reprojecting within {max_reproj_px} px",
    }
    return kept, stats


def build_colmap_model(
    calib: Calibration, tracks: SfmTracks | None = None, max_reproj_px: float = 1.0
) -> tuple[Any, dict[str, Any]]:
    """The pycolmap.Reconstruction of the export (see the module doc) and its statistics."""
    import pycolmap

    rec = pycolmap.Reconstruction()
    views = sorted(calib.views)
    cameras = sorted({v.camera for v in views})
    cam_ids = {c: i for i, c in enumerate(cameras, start=1)}
    first = {c: next(calib.views[v] for v in views if v.camera == c) for c in cameras}
    image_ids = {colmap_image_name(v.group, v.camera): i for i, v in enumerate(views, start=1)}
    kept, stats = _kept_observations(calib, tracks, max_reproj_px)
    keypoints: dict[str, list[tuple[float, float]]] = {n: [] for n in image_ids}
    track_refs: list[list[tuple[int, int]]] = []
    for obs in kept:
        refs = []
        for name, x, y in obs:
            refs.append((image_ids[name], len(keypoints[name])))
            keypoints[name].append((x, y))
        track_refs.append(refs)

    def image(v: ViewId) -> Any:
        name = colmap_image_name(v.group, v.camera)
        kp = np.asarray(keypoints[name], float).reshape(-1, 2)
        return pycolmap.Image(name=name, camera_id=cam_ids[v.camera], image_id=image_ids[name], keypoints=kp)

    rig = rig_structure(calib)
    if rig is None:
        for c in cameras:
            rec.add_camera_with_trivial_rig(_camera(cam_ids[c], first[c]))
        for v in views:
            rec.add_image_with_trivial_frame(image(v), _rigid((calib.views[v].R, calib.views[v].t)))
        stats["rig"] = f"{len(cameras)} one-sensor rigs (the views are not one rigid rig)"
    else:
        sensor_from_rig, rig_from_world = rig
        for c in cameras:
            rec.add_camera(_camera(cam_ids[c], first[c]))
        prig = pycolmap.Rig(rig_id=1)
        prig.add_ref_sensor(pycolmap.sensor_t(pycolmap.SensorType.CAMERA, cam_ids[cameras[0]]))
        for c in cameras[1:]:
            prig.add_sensor(
                pycolmap.sensor_t(pycolmap.SensorType.CAMERA, cam_ids[c]), _rigid(sensor_from_rig[c])
            )
        rec.add_rig(prig)
        frame_ids = {g: i for i, g in enumerate(sorted(rig_from_world), start=1)}
        for g, fid in frame_ids.items():
            frame = pycolmap.Frame(frame_id=fid, rig_id=1, rig_from_world=_rigid(rig_from_world[g]))
            for v in views:
                if v.group == g:
                    frame.add_data_id(image(v).data_id)
            rec.add_frame(frame)
        for v in views:
            im = image(v)
            im.frame_id = frame_ids[v.group]
            rec.add_image(im)
        stats["rig"] = f"one rig of {len(cameras)} sensors (reference {cameras[0]}), {len(frame_ids)} frames"
    for k, refs in enumerate(track_refs):
        if refs:
            track = pycolmap.Track()
            for image_id, idx in refs:
                track.add_element(image_id, idx)
            rec.add_point3D(np.asarray(tracks.xyz[k], float), track, np.asarray(tracks.colors[k], np.uint8))
    if rec.num_points3D():
        rec.update_point_3d_errors()  # so the model's own summary reports the reprojection error
    return rec, stats


def _png_size(path: Path) -> tuple[int, int]:
    """(width, height) from a PNG's IHDR chunk, without decoding the image."""
    with open(path, "rb") as f:
        head = f.read(24)
    if len(head) < 24 or head[:8] != b"\x89PNG\r\n\x1a\n" or head[12:16] != b"IHDR":
        raise LightstageError(f"{path}: not a PNG file")
    return int.from_bytes(head[16:20], "big"), int.from_bytes(head[20:24], "big")


def _link_or_copy(src: Path, dst: Path) -> None:
    """Hard-link `src` to `dst` (instant, no extra space), copying where links are not possible."""
    dst.parent.mkdir(parents=True, exist_ok=True)
    try:
        os.link(src, dst)
    except OSError:
        shutil.copyfile(src, dst)


def write_colmap_images(calib: Calibration, work: WorkDir, out_dir: Path) -> dict[str, Any]:
    """Put each view's well-lit image (and mask, COLMAP's `NAME.png` convention) under out_dir/images and
    out_dir/masks by the model's image names; a size other than the camera's is an error naming the file."""
    written, missing = 0, []
    for v, vc in sorted(calib.views.items()):
        src, mask = work.wellit(v), work.mask(v)
        if not src.is_file():
            missing.append(str(src))
            continue
        pin = vc.camera(DOWNSCALE)
        for path in (src, mask) if mask.is_file() else (src,):
            if _png_size(path) != (pin.width, pin.height):
                raise LightstageError(
                    f"{path}: {_png_size(path)[0]}x{_png_size(path)[1]}, but the camera of view {v} is "
                    f"{pin.width}x{pin.height} at the processed resolution"
                )
        name = colmap_image_name(v.group, v.camera)
        _link_or_copy(src, out_dir / "images" / name)
        if mask.is_file():
            _link_or_copy(mask, out_dir / "masks" / f"{name}.png")
        written += 1
    return {"images_written": written, "images_missing": missing[:10], "images_missing_count": len(missing)}


def write_colmap_model(
    calib: Calibration,
    out_dir: Path,
    tracks: SfmTracks | None = None,
    work: WorkDir | None = None,
    max_reproj_px: float = 1.0,
) -> dict[str, Any]:
    """Write the COLMAP binary model (cameras, images, points3D, rigs, frames .bin; points3D.ply when there
    are points) and, given `work`, the images and masks it names; the folder is replaced as a whole (built
    beside it, then renamed). Returns the statistics for the calibration report."""
    rec, stats = build_colmap_model(calib, tracks, max_reproj_px)
    out_dir = Path(out_dir)
    tmp = out_dir.with_name(out_dir.name + ".tmp")
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    rec.write(tmp)
    if rec.num_points3D():
        rec.export_PLY(str(tmp / "points3D.ply"))
    if work is not None:
        stats.update(write_colmap_images(calib, work, tmp))
    shutil.rmtree(out_dir, ignore_errors=True)
    os.replace(tmp, out_dir)
    stats["path"] = str(out_dir)
    return stats


# ---- nerfstudio ------------------------------------------------------------------------------------------
def _split_views(work: WorkDir | None) -> tuple[list[ViewId], list[ViewId]] | None:
    """(train views, test views) of WORK/split.json, or None without one."""
    if work is None or not work.split.is_file():
        return None
    from lightstage.records.split import load_split

    split = load_split(work.split)
    return split.train.views(), split.test.views()


def transforms_dict(
    calib: Calibration, work: WorkDir | None = None, relative_to: Path | None = None
) -> dict[str, Any]:
    """nerfstudio transforms (per-frame intrinsics, OpenGL camera-to-world, light positions, masks, split)."""

    def rel(path: Path) -> str:
        return os.path.relpath(path, relative_to) if relative_to is not None else str(path)

    frames, names = [], {}
    for view, vc in sorted(calib.views.items()):
        pin = vc.camera(DOWNSCALE)
        d = np.asarray(pin.dist, float)
        file_path = rel(work.wellit(view)) if work is not None else colmap_image_name(view.group, view.camera)
        names[view] = file_path
        frame = {
            "file_path": file_path,
            "group": view.group,
            "camera": view.camera,
            "fl_x": float(pin.K[0, 0]),
            "fl_y": float(pin.K[1, 1]),
            "cx": float(pin.K[0, 2]),
            "cy": float(pin.K[1, 2]),
            "w": int(pin.width),
            "h": int(pin.height),
            "k1": float(d[0]),
            "k2": float(d[1]),
            "p1": float(d[2]),
            "p2": float(d[3]),
            "k3": float(d[4]),
            "transform_matrix": opencv_to_opengl_c2w(vc.R, vc.t).tolist(),
            "light_positions": np.asarray(calib.light_positions[view.group], float).tolist(),
        }
        if work is not None:
            frame["mask_path"] = rel(work.mask(view))
        frames.append(frame)
    out: dict[str, Any] = {
        "camera_model": "OPENCV",
        "convention": "OpenGL camera-to-world (x right, y up, z back); world = lightstage object frame, metres",
        "applied_transform": np.eye(4)[:3].tolist(),  # the world frame is lightstage's, unchanged
        "calibration_method": calib.method,
        "scene_centre": np.asarray(calib.scene_centre, float).tolist(),
        "frames": frames,
    }
    split = _split_views(work)
    if split is not None:
        train, test = ([names[v] for v in vs if v in names] for vs in split)
        out.update(train_filenames=train, val_filenames=test, test_filenames=test)
    ply = work.calibration_dir / "colmap" / "points3D.ply" if work is not None else None
    if ply is not None and ply.is_file():
        out["ply_file_path"] = rel(ply)
    return out


def write_transforms(calib: Calibration, path: Path, work: WorkDir | None = None) -> Path:
    """Write transforms.json (atomically); image paths are relative to its folder."""
    path = Path(path)
    write_json_atomic(path, transforms_dict(calib, work, path.parent))
    return path
