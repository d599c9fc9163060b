"""The per-frame point-light OLAT format of the NeRF and Gaussian-splatting relighting codes: out and in.

A folder with `transforms_train.json` and `transforms_test.json` (NeRF-Blender style), one frame per
(view, light): OpenGL camera-to-world `transform_matrix`, intrinsics (`camera_intrinsics` = [cx, cy, fx, fy],
also as `fl_x fl_y cx cy w h` and OpenCV distortion `k1 k2 p1 p2 k3`), the point light's world position
`pl_pos` (same frame and units as the cameras: metres) and relative RGB `pl_intensity`, and the image
`file_path` + `file_ext` (a half-float RGBA EXR: linear RGB, A = the view's mask) with `mask_path` (PNG
0/255). Field by field, with the loaders it matches: docs/interop.md. A `lightstage` block per frame and per
file carries what the format has no field for (frame ids, the full light table, yaws), so an export imports
back exactly; files of other tools import without it (cameras and lights found by their values).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from lightstage.atomic import write_json_atomic
from lightstage.cameras import opencv_to_opengl_c2w, opengl_c2w_to_opencv
from lightstage.errors import LightstageError
from lightstage.ids import FrameId, ViewId
from lightstage.interop.ingest import ImportedDataset, SourceFrame, image_size, load_json
from lightstage.workdir import DOWNSCALE, WorkDir

FORMAT = "lightstage-olat"
VERSION = 1
PARTS = ("train", "test")


# ---- export ------------------------------------------------------------------------------------------------
def _near_far(calib: Any) -> tuple[float, float]:
    """Ray bounds that hold the scene for every camera: camera distances to the scene centre -+ half the
    nearest one."""
    d = np.array([np.linalg.norm(vc.camera().center - calib.scene_centre) for vc in calib.views.values()])
    r = 0.5 * float(d.min())
    return max(1e-3, float(d.min()) - r), float(d.max()) + r


def _frame_entry(calib: Any, f: FrameId, rel: str, mask_rel: str) -> dict[str, Any]:
    """The frame's fields (module doc); camera and light from the calibration."""
    from lightstage.lights import light_direction

    vc = calib.views[ViewId(f.group, f.camera)]
    pin = vc.camera(DOWNSCALE)
    K, d = pin.K, np.asarray(pin.dist, float)
    pos = np.asarray(calib.light_positions[f.group][f.light], float)
    return {
        "file_path": rel,
        "file_ext": ".exr",
        "mask_path": mask_rel,
        "transform_matrix": opencv_to_opengl_c2w(vc.R, vc.t).tolist(),
        "camera_intrinsics": [float(K[0, 2]), float(K[1, 2]), float(K[0, 0]), float(K[1, 1])],
        "fl_x": float(K[0, 0]),
        "fl_y": float(K[1, 1]),
        "cx": float(K[0, 2]),
        "cy": float(K[1, 2]),
        "w": int(pin.width),
        "h": int(pin.height),
        "k1": float(d[0]),
        "k2": float(d[1]),
        "p1": float(d[2]),
        "p2": float(d[3]),
        "k3": float(d[4]),
        "pl_pos": pos.tolist(),
        "pl_intensity": [1.0, 1.0, 1.0],
        "light_direction": light_direction(pos, calib.scene_centre).tolist(),
        "lightstage": {"group": f.group, "camera": f.camera, "light": int(f.light)},
    }


def _saturation_level(work: WorkDir) -> float | None:
    """The capture's clip level (stage.yaml), None when the capture is not at hand."""
    try:
        from lightstage.capture.layout import open_capture

        return float(open_capture(work.capture_path()).stage.saturation)
    except LightstageError:
        return None


def export_olat(work: WorkDir, out: Path, progress: bool = False) -> dict[str, Any]:
    """Write OUT/transforms_{train,test}.json, frames/<g>/<c>/<lll>.exr, masks/<g>/<c>.png (and
    saturation/<g>/<c>/<lll>.png for frames with clipped pixels) from WORK's processed frames, calibration
    and split."""
    from tqdm import tqdm

    from lightstage.frames import write_exr, write_image
    from lightstage.records.calibration import Calibration
    from lightstage.records.processed import read_mask, read_processed
    from lightstage.records.split import load_split

    calib = Calibration.load(work.calibration)
    split = load_split(work.split)
    out = Path(out)
    near, far = _near_far(calib)
    masks: dict[ViewId, np.ndarray] = {}
    counts = {}
    for part, frameset in (("train", split.train), ("test", split.test)):
        entries = []
        for f in tqdm(list(frameset.frames()), desc=f"export {part}", disable=not progress):
            view = ViewId(f.group, f.camera)
            if view not in calib.views:
                raise LightstageError(f"{work.calibration}: no calibration for view {view} of the split")
            if view not in masks:
                masks[view] = read_mask(work.mask(view))
                write_image(out / "masks" / f.group / f"{f.camera}.png", masks[view].astype(np.uint8) * 255)
            rgb, sat = read_processed(work.frame(f))
            rel = f"frames/{f.group}/{f.camera}/{f.light:03d}"
            alpha = masks[view].astype(np.float32)[..., None]
            write_exr(out / f"{rel}.exr", np.concatenate([rgb, alpha], axis=-1), channels="RGBA")
            entry = _frame_entry(calib, f, rel, f"masks/{f.group}/{f.camera}.png")
            if sat.any():
                sat_rel = f"saturation/{f.group}/{f.camera}/{f.light:03d}.png"
                write_image(out / sat_rel, sat.astype(np.uint8) * 255)
                entry["saturation_path"] = sat_rel
            entries.append(entry)
        doc = {
            "camera_intrinsics": entries[0]["camera_intrinsics"],
            "camera_near": near,
            "camera_far": far,
            "frames": entries,
            "lightstage": {
                "format": FORMAT,
                "version": VERSION,
                "part": part,
                "name": Path(work.root).name,
                "conventions": "world = lightstage object frame (+z up, metres); transform_matrix = OpenGL "
                "camera-to-world (x right, y up, z back); pixel centres at +0.5; images linear HDR",
                "units": "m",
                "scene_centre": np.asarray(calib.scene_centre, float).tolist(),
                "saturation": _saturation_level(work),
                "turntable_axis": {"direction": list(calib.axis.direction), "point": list(calib.axis.point)},
                "yaws_deg": {g: float(y) for g, y in calib.yaws_deg.items()},
                "light_positions": {
                    g: np.asarray(p, float).tolist() for g, p in calib.light_positions.items()
                },
                "split": {"protocol": split.protocol, "source": split.source},
            },
        }
        write_json_atomic(out / f"transforms_{part}.json", doc)
        counts[part] = len(entries)
    return {"format": "olat", "out": str(out), "frames": counts, "views": len(masks)}


# ---- import ------------------------------------------------------------------------------------------------
def _array(value: Any, shape: tuple[int, ...], what: str) -> np.ndarray:
    """`value` as a float array of `shape`, or one error naming `what`."""
    try:
        a = np.asarray(value, float)
    except (TypeError, ValueError):
        a = None
    if a is None or a.shape != shape or not np.all(np.isfinite(a)):
        raise LightstageError(
            f"{what}: expected {len(shape) and 'x'.join(map(str, shape))} numbers, got {value!r}"
        )
    return a


def _image_path(root: Path, frame: dict[str, Any], where: str) -> Path:
    """The frame's image: `img_path`, or `file_path` (+ `file_ext`, or the first of .png/.exr that exists)."""
    if "img_path" in frame:
        return root / str(frame["img_path"])
    if "file_path" not in frame:
        raise LightstageError(f"{where}: no file_path")
    base = root / str(frame["file_path"])
    if base.suffix.lower() in (".exr", ".png", ".jpg", ".jpeg"):
        return base
    exts = [frame["file_ext"]] if "file_ext" in frame else [".png", ".exr"]  # the loaders default to .png
    for ext in exts:
        if Path(f"{base}{ext}").is_file():
            return Path(f"{base}{ext}")
    return Path(f"{base}{exts[0]}")


def _intrinsics(doc: dict, frame: dict, image: Path, where: str) -> np.ndarray:
    """K (3x3, the image's pixels) from the frame's or the file's camera_intrinsics / fl_x.. / camera_angle_x."""
    for src in (frame, doc):
        if "camera_intrinsics" in src:
            cx, cy, fx, fy = _array(src["camera_intrinsics"], (4,), f"{where}: camera_intrinsics")
            return np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])
        if all(k in src for k in ("fl_x", "fl_y", "cx", "cy")):
            fx, fy, cx, cy = (float(src[k]) for k in ("fl_x", "fl_y", "cx", "cy"))
            return np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])
        if "camera_angle_x" in src:
            w, h = image_size(image, where)
            f = 0.5 * w / np.tan(0.5 * float(src["camera_angle_x"]))
            return np.array([[f, 0, w / 2], [0, f, h / 2], [0, 0, 1.0]])
    raise LightstageError(f"{where}: no intrinsics (camera_intrinsics, fl_x/fl_y/cx/cy or camera_angle_x)")


def _part_file(root: Path, part: str) -> Path:
    path = root / f"transforms_{part}.json"
    if part == "test" and not path.is_file() and (root / "transforms_val.json").is_file():
        return root / "transforms_val.json"  # datasets with a validation file only
    if not path.is_file():
        raise LightstageError(
            f"{path}: missing (the format has transforms_train.json and transforms_test.json)"
        )
    return path


def read_olat(root: Path) -> ImportedDataset:
    """The per-frame point-light format at `root` as an ImportedDataset (one error line naming the file for a
    missing image, a frame without pl_pos, a malformed field)."""
    root = Path(root)
    if not root.is_dir():
        raise LightstageError(f"{root}: not a directory (give the folder of transforms_train.json)")
    cam_keys: dict[tuple, ViewId] = {}
    light_keys: dict[tuple, int] = {}
    cameras: dict[ViewId, tuple] = {}
    masks: dict[ViewId, Path | None] = {}
    frames: list[SourceFrame] = []
    block: dict[str, Any] = {}
    kinds = set()
    positions: dict[str, dict[int, np.ndarray]] = {}
    for part in PARTS:
        path = _part_file(root, part)
        doc = load_json(path)
        if not isinstance(doc, dict) or not isinstance(doc.get("frames"), list):
            raise LightstageError(f"{path}: expected a mapping with a 'frames' list")
        block = block or (doc.get("lightstage") if isinstance(doc.get("lightstage"), dict) else {})
        for i, fr in enumerate(doc["frames"]):
            where = f"{path.name} frame {i}"
            if not isinstance(fr, dict):
                raise LightstageError(f"{path}: frame {i}: expected a mapping")
            image = _image_path(root, fr, f"{path}: frame {i}")
            if not image.is_file():
                raise LightstageError(f"{image}: missing ({where})")
            kinds.add("linear" if image.suffix.lower() == ".exr" else "srgb")
            if "transform_matrix" not in fr:
                raise LightstageError(f"{path}: frame {i} has no transform_matrix")
            c2w = np.asarray(fr["transform_matrix"], float) if fr["transform_matrix"] is not None else None
            if c2w is None or c2w.shape not in ((4, 4), (3, 4)):
                raise LightstageError(f"{path}: frame {i}: transform_matrix must be 4x4 or 3x4")
            R, t = opengl_c2w_to_opencv(np.vstack([c2w[:3], [0, 0, 0, 1]]))
            K = _intrinsics(doc, fr, image, f"{path}: frame {i}")
            dist = np.array([float(fr.get(k, 0.0)) for k in ("k1", "k2", "p1", "p2", "k3")])
            if fr.get("pl_pos") is None:
                raise LightstageError(f"{path}: frame {i} has no pl_pos (the point light's position)")
            pos = _array(fr["pl_pos"], (3,), f"{path}: frame {i}: pl_pos")
            ids = fr.get("lightstage") if isinstance(fr.get("lightstage"), dict) else None
            if ids is not None:
                try:
                    view, light = ViewId(str(ids["group"]), str(ids["camera"])), int(ids["light"])
                except (KeyError, TypeError, ValueError):
                    raise LightstageError(
                        f"{path}: frame {i}: lightstage needs group, camera, light"
                    ) from None
            else:
                key = (*np.round(c2w[:3].ravel(), 9), *np.round(K.ravel(), 6))
                view = cam_keys.setdefault(key, ViewId("000", f"cam{len(cam_keys):03d}"))
                light = light_keys.setdefault(tuple(np.round(pos, 9)), len(light_keys))
            if view in cameras:
                K0, R0, t0, _ = cameras[view]
                if np.abs(R0 - R).max() > 1e-9 or np.abs(t0 - t).max() > 1e-9 or np.abs(K0 - K).max() > 1e-6:
                    raise LightstageError(
                        f"{path}: frame {i}: camera of view {view} differs from its earlier frames"
                    )
            cameras.setdefault(view, (K, R, t, dist))
            known = positions.setdefault(view.group, {})
            if light in known and np.abs(known[light] - pos).max() > 1e-6:
                raise LightstageError(f"{path}: frame {i}: light {light} of group {view.group} moved")
            known[light] = pos
            if view not in masks:
                masks[view] = root / str(fr["mask_path"]) if fr.get("mask_path") else None
            sat = root / str(fr["saturation_path"]) if fr.get("saturation_path") else None
            frames.append(SourceFrame(FrameId(view.group, view.camera, light), image, part, where, sat))
    if len(kinds) > 1:
        raise LightstageError(f"{root}: mixes EXR and 8-bit images; give one kind")
    light_positions = _light_table(block, positions, root)
    encoding = kinds.pop()
    saturation = block.get("saturation") or (None if encoding == "srgb" else 65504.0)
    return ImportedDataset(
        name=str(block.get("name") or root.name),
        format="olat",
        source=root,
        cameras=cameras,
        light_positions=light_positions,
        frames=frames,
        masks=masks,
        encoding=encoding,
        yaws_deg={str(g): float(y) for g, y in (block.get("yaws_deg") or {}).items()},
        scene_centre=np.asarray(block.get("scene_centre", [0.0, 0.0, 0.0]), float),
        saturation=float(saturation) if saturation else None,
        units=str(block.get("units", "unknown")),
        notes=[] if block else ["cameras and lights identified by their values (no lightstage block)"],
    )


def _light_table(block: dict, seen: dict[str, dict[int, np.ndarray]], root: Path) -> dict[str, np.ndarray]:
    """Per group (L, 3) light positions: the lightstage block's full table (checked against every frame's
    pl_pos), or the positions the frames give (indices 0..L-1 all used)."""
    table = block.get("light_positions")
    if isinstance(table, dict):
        out = {
            str(g): _array(
                p, (len(p) if isinstance(p, list) else -1, 3), f"{root}: lightstage.light_positions.{g}"
            )
            for g, p in table.items()
        }
        for g, known in seen.items():
            for light, pos in known.items():
                if g not in out or light >= len(out[g]) or np.abs(out[g][light] - pos).max() > 1e-6:
                    raise LightstageError(
                        f"{root}: light {light} of group {g}: pl_pos differs from the light table"
                    )
        return out
    out = {}
    for g, known in seen.items():
        if sorted(known) != list(range(len(known))):
            raise LightstageError(f"{root}: group {g}: light indices {sorted(known)[:5]}... are not 0..L-1")
        out[g] = np.stack([known[i] for i in range(len(known))])
    return out
