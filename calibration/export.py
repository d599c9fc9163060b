"""Exports of a calibration for other tools: a COLMAP sparse model and a nerfstudio-style transforms.json.

Both are in the world frame of the conventions (metres) at the processed resolution (raw / 4), with image
names `<camera>/<group>.png` (COLMAP) and paths to the well-lit images (nerfstudio). The nerfstudio file uses the
OpenGL camera convention (`lightstage.cameras.opencv_to_opengl_c2w`) and carries per-frame light positions.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

from lightstage.atomic import write_json_atomic
from lightstage.cameras import opencv_to_opengl_c2w
from lightstage.records.calibration import Calibration
from lightstage.workdir import DOWNSCALE, WorkDir


def colmap_image_name(group: str, camera: str) -> str:
    """Image name of a view inside the exported COLMAP model."""
    return f"{camera}/{group}.png"


def write_colmap_model(
    calib: Calibration, out_dir: Path, points: np.ndarray | None = None, colors: np.ndarray | None = None
) -> Path:
    """Write a COLMAP binary sparse model (cameras.bin, images.bin, points3D.bin, rigs.bin, frames.bin).

    One COLMAP camera per stage camera (PINHOLE, or OPENCV with distortion), one image per view with its
    world-to-camera pose; optional 3D points (world frame) without tracks, for viewing.
    """
    import pycolmap

    rec = pycolmap.Reconstruction()
    cam_ids: dict[str, int] = {}
    for view, vc in sorted(calib.views.items()):
        if view.camera in cam_ids:
            continue
        cam_ids[view.camera] = len(cam_ids) + 1
        pin = vc.camera(DOWNSCALE)
        K, d = pin.K, np.asarray(pin.dist, dtype=np.float64)
        has_dist = bool(np.any(d != 0))
        cam = pycolmap.Camera.create_from_model_name(
            cam_ids[view.camera], "OPENCV" if has_dist else "PINHOLE", float(K[0, 0]), pin.width, pin.height
        )
        params = [K[0, 0], K[1, 1], K[0, 2], K[1, 2]]
        if has_dist:
            params += [d[0], d[1], d[2], d[3]]
        cam.params = params
        rec.add_camera_with_trivial_rig(cam)
    for image_id, (view, vc) in enumerate(sorted(calib.views.items()), start=1):
        image = pycolmap.Image(
            name=colmap_image_name(view.group, view.camera), camera_id=cam_ids[view.camera], image_id=image_id
        )
        pose = pycolmap.Rigid3d(pycolmap.Rotation3d(np.asarray(vc.R, float)), np.asarray(vc.t, float))
        rec.add_image_with_trivial_frame(image, pose)
    if points is not None:
        cols = np.zeros((len(points), 3), np.uint8) if colors is None else np.asarray(colors, np.uint8)
        for xyz, rgb in zip(np.asarray(points, float), cols, strict=True):
            rec.add_point3D(xyz, pycolmap.Track(), rgb)
    out_dir = Path(out_dir)
    tmp = out_dir.with_name(out_dir.name + ".tmp")
    if tmp.exists():
        import shutil

        shutil.rmtree(tmp)
    tmp.mkdir(parents=True)
    rec.write(tmp)
    if out_dir.exists():
        import shutil

        shutil.rmtree(out_dir)
    os.replace(tmp, out_dir)
    return out_dir


def transforms_dict(
    calib: Calibration, work: WorkDir | None = None, relative_to: Path | None = None
) -> dict[str, Any]:
    """nerfstudio-style transforms (per-frame intrinsics, OpenGL camera-to-world, light positions)."""
    frames = []
    for view, vc in sorted(calib.views.items()):
        pin = vc.camera(DOWNSCALE)
        d = np.asarray(pin.dist, float)
        if work is not None:
            path = work.wellit(view)
            file_path = os.path.relpath(path, relative_to) if relative_to is not None else str(path)
        else:
            file_path = colmap_image_name(view.group, view.camera)
        frames.append(
            {
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
        )
    return {
        "camera_model": "OPENCV",
        "convention": "OpenGL camera-to-world (x right, y up, z back); world = lightstage object frame, metres",
        "calibration_method": calib.method,
        "scene_centre": np.asarray(calib.scene_centre, float).tolist(),
        "frames": frames,
    }


def write_transforms(calib: Calibration, path: Path, work: WorkDir | None = None) -> Path:
    """Write transforms.json (atomically); image paths are relative to its folder."""
    path = Path(path)
    write_json_atomic(path, transforms_dict(calib, work, path.parent))
    return path
