"""OpenIllumination's OLAT layout in (Liu et al., NeurIPS 2023 Datasets; docs/interop.md for the sources):

```
OBJ/                                        e.g. OpenIllumination/OLAT/obj_01_egg
  output/transforms_train.json              {"frames": {CAMERA: {"transform_matrix": 4x4, "camera_angle_x": rad}}}
  output/transforms_test.json               the same for the held-out cameras
  output/obj_masks/CAMERA.png               object masks (com_masks/: object + support, the fallback)
  Lights/NNN/raw_undistorted/CAMERA.JPG     one folder per OLAT light (000..141), undistorted sRGB JPEG
OpenIllumination/light_pos.npy              (142, 3) light positions, one global table for every object
```

Frames are keyed by camera (one transform per camera, every light), `transform_matrix` is a Blender/OpenGL
camera-to-world, the principal point is the image centre and the focal length 0.5 W / tan(camera_angle_x / 2).
Light folder NNN is row NNN of light_pos.npy, in the cameras' frame (the dataset's normalised units, not
metres). The split keeps the dataset's train/test cameras; lightstage's test lights must be unseen, so the
lights are split too: the paper's test-light placement scaled to the lights present, every other light trains.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from lightstage.cameras import opengl_c2w_to_opencv
from lightstage.errors import LightstageError
from lightstage.ids import FrameId, ViewId
from lightstage.interop.ingest import ImportedDataset, SourceFrame, image_size, load_json
from lightstage.npyio import load_npy

LIGHT_TABLE = "light_pos.npy"
IMAGE_EXTS = (".JPG", ".jpg", ".jpeg", ".png")


def find_light_table(obj: Path, given: Path | None) -> Path:
    """The global light table: `given`, else light_pos.npy in OBJ or two folders up (the release layout)."""
    candidates = (
        [given]
        if given is not None
        else [obj / LIGHT_TABLE, obj.parent / LIGHT_TABLE, obj.parent.parent / LIGHT_TABLE]
    )
    for c in candidates:
        if c.is_file():
            return c
    raise LightstageError(
        f"{candidates[0]}: missing (OpenIllumination's light positions; looked in "
        f"{', '.join(str(c.parent) for c in candidates)}; give --lights FILE)"
    )


def load_light_table(path: Path) -> np.ndarray:
    """(L, 3) light positions from a .npy file, or one error line naming it."""
    try:
        table = load_npy(path)
    except (OSError, ValueError) as e:
        raise LightstageError(f"{path}: not a readable .npy array ({e})") from None
    if table.ndim != 2 or table.shape[1] != 3 or not np.all(np.isfinite(table)):
        raise LightstageError(f"{path}: expected (L, 3) finite light positions, got shape {table.shape}")
    return table.astype(np.float64)


def _frames_of(path: Path) -> dict[str, Any]:
    doc = load_json(path)
    if not isinstance(doc, dict) or not isinstance(doc.get("frames"), dict) or not doc["frames"]:
        raise LightstageError(
            f"{path}: expected {{'frames': {{CAMERA: {{transform_matrix, camera_angle_x}}}}}}"
        )
    return doc["frames"]


def _image(obj: Path, folder: str, camera: str) -> Path:
    """Lights/NNN/raw_undistorted/CAMERA with the first extension that exists (the .JPG path when none)."""
    base = obj / "Lights" / folder / "raw_undistorted"
    for ext in IMAGE_EXTS:
        if (base / f"{camera}{ext}").is_file():
            return base / f"{camera}{ext}"
    return base / f"{camera}{IMAGE_EXTS[0]}"


def _camera(entry: Any, image: Path, where: str) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(K, R, t, dist) of one camera entry, K at the image's resolution (its size from the file's header)."""
    if not isinstance(entry, dict) or "transform_matrix" not in entry or "camera_angle_x" not in entry:
        raise LightstageError(f"{where}: needs transform_matrix and camera_angle_x")
    c2w = np.asarray(entry["transform_matrix"], float)
    if c2w.shape != (4, 4) or not np.all(np.isfinite(c2w)):
        raise LightstageError(f"{where}: transform_matrix must be 4x4 finite numbers")
    w, h = image_size(image, where)
    f = 0.5 * w / np.tan(0.5 * float(entry["camera_angle_x"]))
    K = np.array([[f, 0.0, w / 2.0], [0.0, f, h / 2.0], [0.0, 0.0, 1.0]])
    R, t = opengl_c2w_to_opencv(c2w)
    return K, R, t, np.zeros(5)


def read_openillumination(obj: Path, lights: Path | None = None) -> ImportedDataset:
    """One OpenIllumination object folder (module doc) as an ImportedDataset: group 000, its cameras, the
    lights whose folders are present (renumbered 0..L-1 in folder order; the report lists the mapping)."""
    from lightstage.dataset.protocols import paper_light_counts, place_test_lights

    obj = Path(obj)
    if not obj.is_dir():
        raise LightstageError(f"{obj}: not a directory (give an object folder such as OLAT/obj_01_egg)")
    table_path = find_light_table(obj, lights)
    table = load_light_table(table_path)
    lights_dir = obj / "Lights"
    folders = sorted(p.name for p in lights_dir.iterdir() if p.is_dir()) if lights_dir.is_dir() else []
    if not folders:
        raise LightstageError(f"{lights_dir}: no light folders (Lights/NNN/raw_undistorted/CAMERA.JPG)")
    for name in folders:
        if not name.isdigit():
            raise LightstageError(f"{lights_dir / name}: light folders are named by number (000..)")
        if int(name) >= len(table):
            raise LightstageError(
                f"{table_path}: {len(table)} light positions, but {lights_dir / name} exists"
            )
    if len(folders) < 2:
        raise LightstageError(f"{lights_dir}: {len(folders)} light; train and test lights need at least 2")
    parts = {p: _frames_of(obj / "output" / f"transforms_{p}.json") for p in ("train", "test")}
    n_test = paper_light_counts(len(folders))[1]
    test_lights = set(place_test_lights(n_test, len(folders)))
    cameras, masks, frames = {}, {}, []
    for part, entries in parts.items():
        for cam, entry in entries.items():
            view = ViewId("000", str(cam))
            if view in cameras:
                raise LightstageError(f"{obj / 'output'}: camera {cam} is in both transforms_train and _test")
            where = f"output/transforms_{part}.json camera {cam}"
            cameras[view] = _camera(entry, _image(obj, folders[0], str(cam)), where)
            mask = obj / "output" / "obj_masks" / f"{cam}.png"
            masks[view] = mask if mask.is_file() else obj / "output" / "com_masks" / f"{cam}.png"
            if not masks[view].is_file():
                raise LightstageError(
                    f"{mask}: missing (the mask of camera {cam}; com_masks/ has none either)"
                )
            for k, folder in enumerate(folders):
                if (k in test_lights) != (part == "test"):
                    continue
                image = _image(obj, folder, str(cam))
                if not image.is_file():
                    raise LightstageError(f"{image}: missing (camera {cam} under light {folder})")
                frames.append(
                    SourceFrame(FrameId("000", str(cam), k), image, part, f"{where}, light {folder}")
                )
    return ImportedDataset(
        name=obj.name,
        format="openillumination",
        source=obj,
        cameras=cameras,
        light_positions={"000": table[[int(f) for f in folders]]},
        frames=frames,
        masks=masks,
        encoding="srgb",
        saturation=1.0,
        units="OpenIllumination's normalised frame (not metres)",
        notes=[
            f"light table {table_path}",
            "lights renumbered in folder order: "
            + ", ".join(f"{k}=Lights/{f}" for k, f in enumerate(folders[:20]))
            + (" ..." if len(folders) > 20 else ""),
            f"test lights (unseen in training): {sorted(int(folders[k]) for k in test_lights)}",
            "images are sRGB JPEG, linearised on import; full-scale samples flagged saturated",
        ],
    )
