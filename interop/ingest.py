"""The work directory an import writes: what the stages after preprocess read, from an external OLAT dataset.

A reader (`olat.read_olat`, `openillumination.read_openillumination`) turns a dataset into an
`ImportedDataset` — cameras, point lights, one source image per (group, camera, light) frame, masks and the
train/test parts — and `write_work` writes WORK:

```
WORK/capture/stage.yaml, capture.yaml   # a stage synthesised from the data (no raw frames); capture.txt names it
WORK/preprocess/frames/<g>/<c>/<l>.exr  # the images as processed frames (linear RGB + saturation flags)
WORK/preprocess/views/<g>/<c>/          # mask.png, zones.png, wellit.png (tonemapped mean of the view's frames)
WORK/calibration/calibration.json       # method "imported"
WORK/split.json                         # the dataset's train/test frames (split protocol "imported")
WORK/reports/preprocess.json            # frames of the cross product the data lacks (split exclusions)
WORK/reports/import.json, WORK/import.yaml  # what was imported; the pipeline config that reruns split..eval
```

`lightstage run WORK/import.yaml --from split` then reruns split (the inline protocol + exclusions reproduce
split.json exactly), bounds, shard, train and eval. Every problem is one LightstageError naming the file.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from lightstage.atomic import write_json_atomic, write_text_atomic
from lightstage.cameras import scale_intrinsics
from lightstage.errors import LightstageError
from lightstage.ids import FrameId, ViewId
from lightstage.rig import TurntableAxis
from lightstage.workdir import DOWNSCALE, WorkDir

ZONE_BAND_PX = 6  # the preprocess stage's default zone band (PreprocessConfig.band_width)


@dataclass(frozen=True)
class SourceFrame:
    """One frame of the dataset: its id in WORK, source image, part and where it was listed (for errors)."""

    frame: FrameId
    image: Path
    part: str  # "train" | "test"
    where: str
    saturation: Path | None = None  # PNG of the frame's saturated pixels (non-zero), lightstage's own export


@dataclass
class ImportedDataset:
    """An external dataset in lightstage terms; intrinsics at the images' resolution (pixel centres at +0.5)."""

    name: str
    format: str
    source: Path
    cameras: dict[ViewId, tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]]  # view -> K, R, t, dist
    light_positions: dict[str, np.ndarray]  # group -> (L, 3), world frame
    frames: list[SourceFrame]
    masks: dict[ViewId, Path | None]  # None: the alpha channel of the view's first frame
    encoding: str = "linear"  # "linear" (EXR) | "srgb" (8/16-bit images, linearised on import)
    yaws_deg: dict[str, float] = field(default_factory=dict)
    axis: TurntableAxis = field(default_factory=TurntableAxis)
    scene_centre: np.ndarray = field(default_factory=lambda: np.zeros(3))
    saturation: float | None = None  # clip level of linear sources (None: 1.0 for sRGB sources)
    units: str = "m"
    notes: list[str] = field(default_factory=list)


# ---- images ------------------------------------------------------------------------------------------------
def image_size(path: Path, where: str) -> tuple[int, int]:
    """(width, height) of an image file from its header; a missing or unreadable file names `where`."""
    if not path.is_file():
        raise LightstageError(f"{path}: missing ({where})")
    if path.suffix.lower() == ".exr":
        from lightstage.frames import read_exr_header

        h = read_exr_header(path)
        return h.width, h.height
    import OpenImageIO as oiio

    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        raise LightstageError(f"{path}: cannot open image ({where}): {oiio.geterror() or 'unknown format'}")
    try:
        return inp.spec().width, inp.spec().height
    finally:
        inp.close()


def srgb_decode(x: np.ndarray) -> np.ndarray:
    """Inverse sRGB OETF (IEC 61966-2-1): display values in [0, 1] -> linear."""
    x = np.clip(np.asarray(x, np.float32), 0.0, 1.0)
    return np.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4).astype(np.float32)


def read_source(path: Path, encoding: str) -> tuple[np.ndarray, np.ndarray | None, np.ndarray]:
    """(linear RGB float32, alpha or None, saturated bool) of a source image. sRGB sources are linearised and
    their full-scale samples (1.0) flagged as saturated; linear EXRs carry no flags of their own."""
    from lightstage.frames import read_exr_header, read_image

    if path.suffix.lower() == ".exr":
        from lightstage.frames import read_exr

        names = {c for part in read_exr_header(path).part_channels for c in part}
        chans = "RGBA" if "A" in names else "RGB"
        img = read_exr(path, channels=chans).astype(np.float32)
        alpha = img[..., 3] if chans == "RGBA" else None
        return np.ascontiguousarray(img[..., :3]), alpha, np.zeros(img.shape[:2], bool)
    img = read_image(path)
    if img.shape[2] < 3:
        img = np.repeat(img[..., :1], 3, axis=2) if img.shape[2] == 1 else img
    rgb = img[..., :3]
    alpha = img[..., 3] if img.shape[2] >= 4 else None
    sat = np.any(rgb >= 1.0, axis=-1)
    return (srgb_decode(rgb) if encoding == "srgb" else rgb.astype(np.float32)), alpha, sat


def _downscale(img: np.ndarray, n: int) -> np.ndarray:
    """Area mean over n x n blocks (float32; exact for the sizes checked by `write_work`)."""
    if n == 1:
        return img
    h, w = img.shape[:2]
    return (
        img.reshape(h // n, n, w // n, n, *img.shape[2:])
        .mean(axis=(1, 3), dtype=np.float64)
        .astype(np.float32)
    )


# ---- checks ------------------------------------------------------------------------------------------------
def check_dataset(ds: ImportedDataset, downscale: int) -> tuple[int, int]:
    """The images' common (width, height) after every file, light and size has been checked (one error line
    naming the file otherwise)."""
    if not ds.frames:
        raise LightstageError(f"{ds.source}: no frames to import")
    seen: dict[FrameId, str] = {}
    size: tuple[int, int] | None = None
    first: str = ""
    for f in ds.frames:
        if f.frame in seen:
            raise LightstageError(
                f"{ds.source}: frame {f.frame} listed twice ({seen[f.frame]} and {f.where})"
            )
        seen[f.frame] = f.where
        view = ViewId(f.frame.group, f.frame.camera)
        if view not in ds.cameras:
            raise LightstageError(f"{ds.source}: {f.where}: no camera for view {view}")
        pos = ds.light_positions.get(f.frame.group)
        if pos is None or not 0 <= f.frame.light < len(pos):
            raise LightstageError(f"{ds.source}: {f.where}: light {f.frame.light} has no position")
        wh = image_size(f.image, f.where)
        if size is None:
            size, first = wh, str(f.image)
        elif wh != size:
            raise LightstageError(
                f"{f.image}: {wh[0]}x{wh[1]}, but {first} is {size[0]}x{size[1]} (sizes differ)"
            )
    assert size is not None
    for view, mask in ds.masks.items():
        if mask is not None and image_size(mask, f"mask of view {view}") != size:
            m = image_size(mask, "")
            raise LightstageError(f"{mask}: mask is {m[0]}x{m[1]}, the images {size[0]}x{size[1]}")
    views = {ViewId(f.frame.group, f.frame.camera) for f in ds.frames}
    lacking = sorted(v for v in views if v not in ds.masks)
    if lacking:
        raise LightstageError(
            f"{ds.source}: no mask for view {lacking[0]} ({len(lacking)} views without one)"
        )
    if size[0] % downscale or size[1] % downscale:
        raise LightstageError(f"--downscale {downscale}: does not divide the images' {size[0]}x{size[1]}")
    return size


# ---- records -----------------------------------------------------------------------------------------------
def make_stage(ds: ImportedDataset, width: int, height: int, saturation: float) -> Any:
    """A stage.yaml for the data (processed width x height): every camera at its first view's pose, the
    lights at the first group's positions, the groups with their yaws; raw = processed x DOWNSCALE."""
    from lightstage.capture.stage import CameraSpec, GroupSpec, LightSpec, Stage

    cams = []
    for cam in sorted({v.camera for v in ds.cameras}):
        v = min(v for v in ds.cameras if v.camera == cam)
        K, R, t, dist = ds.cameras[v]
        k = scale_intrinsics(K, DOWNSCALE)
        cams.append(CameraSpec(cam, k[0, 0], k[1, 1], k[0, 2], k[1, 2], R, t, dist if np.any(dist) else None))
    groups = sorted(ds.light_positions)
    pos = np.asarray(ds.light_positions[groups[0]], float)
    lights = tuple(LightSpec(i, p) for i, p in enumerate(pos))
    radius = float(np.median(np.linalg.norm(pos - ds.scene_centre, axis=1))) or 1.5
    return Stage(
        name=f"imported-{ds.name}",
        cameras=tuple(cams),
        lights=lights,
        groups=tuple(GroupSpec(g, float(ds.yaws_deg.get(g, 0.0)) % 360.0) for g in groups),
        width=width * DOWNSCALE,
        height=height * DOWNSCALE,
        saturation=float(saturation),
        sphere_radius=radius,
        centre_height=max(1.1, 1.0 - float(pos[:, 2].min())),
        axis=ds.axis,
    )


def make_split(ds: ImportedDataset, stage: Any) -> tuple[Any, dict[str, Any], list[FrameId]]:
    """(split, inline protocol, excluded frames): the dataset's parts as a protocol of explicit cameras, lights
    and groups whose cross product, less the frames the data lacks, is exactly its frames (what
    `lightstage split` resolves again from import.yaml and the exclusions in reports/preprocess.json)."""
    from lightstage.dataset.protocols import protocol_from_dict, resolve

    parts = {p: {f.frame for f in ds.frames if f.part == p} for p in ("train", "test")}
    for p, frames in parts.items():
        if not frames:
            raise LightstageError(f"{ds.source}: the dataset has no {p} frames")
    spec: dict[str, Any] = {"name": "imported", "base": "paper"}
    excluded: set[FrameId] = set()
    for key, attr in (("cameras", "camera"), ("lights", "light"), ("groups", "group")):
        spec[key] = {p: sorted({getattr(f, attr) for f in frames}) for p, frames in parts.items()}
    for p, frames in parts.items():
        for g in spec["groups"][p]:
            for c in spec["cameras"][p]:
                for lt in spec["lights"][p]:
                    if FrameId(g, c, lt) not in frames:
                        excluded.add(FrameId(g, c, lt))
    shared = set(spec["cameras"]["train"]) & set(spec["cameras"]["test"])
    if shared:
        raise LightstageError(
            f"{ds.source}: camera(s) {', '.join(sorted(shared)[:5])} appear in both train and test frames; "
            "lightstage's test views must be unseen in training"
        )
    protocol = protocol_from_dict(spec, f"{ds.source} (import)")
    split = resolve(protocol, stage, excluded, source=f"imported from {ds.source}")
    return split, spec, sorted(excluded)


def _wellit(mean: np.ndarray, exposure: float) -> np.ndarray:
    from lightstage.tonemap import tonemap_u8

    return tonemap_u8(mean, exposure)


def write_work(
    ds: ImportedDataset, work: WorkDir, downscale: int = 1, progress: bool = False
) -> dict[str, Any]:
    """Write WORK from the dataset (module doc); refuses a WORK that already holds processed data."""
    from tqdm import tqdm

    from lightstage.capture.layout import CaptureInfo, save_capture_info
    from lightstage.frames import write_image
    from lightstage.preprocess.segment import zone_map
    from lightstage.records.calibration import Calibration, ViewCalibration
    from lightstage.records.processed import to_half, write_processed
    from lightstage.tonemap import auto_exposure

    t0 = time.perf_counter()
    for existing in (work.preprocess_dir, work.calibration_dir, work.split):
        if existing.exists():
            raise LightstageError(
                f"{existing}: WORK already holds a work directory's data; import into a new one"
            )
    if downscale < 1:
        raise LightstageError(f"--downscale must be >= 1, got {downscale}")
    w0, h0 = check_dataset(ds, downscale)
    width, height = w0 // downscale, h0 // downscale
    saturation = ds.saturation if ds.saturation is not None else 1.0
    stage = make_stage(ds, width, height, saturation)
    split, protocol, excluded = make_split(ds, stage)

    capture = work.root / "capture"
    capture.mkdir(parents=True, exist_ok=True)
    stage.save(capture / "stage.yaml")
    info = CaptureInfo(
        object_name=ds.name, notes={"imported": {"format": ds.format, "source": str(ds.source)}}
    )
    save_capture_info(info, capture / "capture.yaml")
    work.link_capture(capture)

    views = sorted({ViewId(f.frame.group, f.frame.camera) for f in ds.frames})
    sums = {v: np.zeros((height, width, 3), np.float64) for v in views}
    counts = dict.fromkeys(views, 0)
    alphas: dict[ViewId, np.ndarray] = {}
    n_sat = 0
    for f in tqdm(sorted(ds.frames, key=lambda f: f.frame), desc="import", disable=not progress):
        view = ViewId(f.frame.group, f.frame.camera)
        rgb, alpha, sat = read_source(f.image, ds.encoding)
        if f.saturation is not None:
            from lightstage.records.processed import read_mask

            sat = read_mask(f.saturation)
        rgb, sat = _downscale(rgb, downscale), _downscale(sat.astype(np.float32), downscale) > 0
        if alpha is not None and view not in alphas:
            alphas[view] = _downscale(alpha.astype(np.float32), downscale) > 0.5
        if not np.all(np.isfinite(rgb)) or rgb.min() < 0:
            raise LightstageError(f"{f.image}: non-finite or negative samples ({f.where})")
        planes = to_half(np.ascontiguousarray(rgb.transpose(2, 0, 1)))
        write_processed(work.frame(f.frame), planes, sat, "zip", {"lightstage_imported_from": str(f.image)})
        sums[view] += planes.transpose(1, 2, 0).astype(np.float64)
        counts[view] += 1
        n_sat += int(sat.sum())

    masks = {}
    for v in views:
        src = ds.masks.get(v)
        if src is not None:
            from lightstage.records.processed import read_mask

            m = _downscale(read_mask(src).astype(np.float32), downscale) > 0.5
        elif v in alphas:
            m = alphas[v]
        else:
            raise LightstageError(f"{ds.source}: view {v} has neither a mask file nor an alpha channel")
        masks[v] = m
        work.view_dir(v).mkdir(parents=True, exist_ok=True)
        write_image(work.mask(v), m.astype(np.uint8) * 255)
        write_image(work.zones(v), zone_map(m, ZONE_BAND_PX))
    means = {v: (sums[v] / max(1, counts[v])).astype(np.float32) for v in views}
    fg = np.concatenate(
        [means[v][masks[v]] for v in views if masks[v].any()] or [np.ones((1, 3), np.float32)]
    )
    exposure = auto_exposure(fg[None], 99.0)
    for v in views:
        write_image(work.wellit(v), _wellit(means[v], exposure))

    calib_views = {}
    for v in views:
        K, R, t, dist = ds.cameras[v]
        K_raw = scale_intrinsics(np.asarray(K, float), DOWNSCALE / downscale)
        calib_views[v] = ViewCalibration(K_raw, np.asarray(R, float), np.asarray(t, float), width * DOWNSCALE,
                                         height * DOWNSCALE, np.asarray(dist, float))  # fmt: skip
    calib = Calibration(
        "imported",
        calib_views,
        {g: np.asarray(p, float) for g, p in ds.light_positions.items()},
        ds.axis,
        {g: float(ds.yaws_deg.get(g, 0.0)) for g in ds.light_positions},
        np.asarray(ds.scene_centre, float),
    )
    calib.save(work.calibration)
    split.save(work.split)
    write_json_atomic(
        work.report("preprocess"),
        {
            "stage": "preprocess",
            "imported": True,
            "note": "written by `lightstage import`: the frames below are in the split's cross product but not "
            "in the imported data",
            "rejected_frames": [str(f) for f in excluded],
        },
    )
    config = {
        "capture": "capture",
        "work": ".",
        "split": {"protocol": protocol},
    }
    header = (
        f"# Written by `lightstage import {ds.format}` from {ds.source}.\n"
        f"# Train and evaluate on it: lightstage run {work.root / 'import.yaml'} --from split\n"
    )
    write_text_atomic(work.root / "import.yaml", header + yaml.safe_dump(config, sort_keys=False))
    summary = {
        "stage": "import",
        "format": ds.format,
        "source": str(ds.source),
        "units": ds.units,
        "encoding": ds.encoding,
        "downscale": downscale,
        "resolution": [width, height],
        "views": len(views),
        "lights": {g: len(p) for g, p in ds.light_positions.items()},
        "frames": len(ds.frames),
        "saturated_pixels": n_sat,
        "counts": split.counts(),
        "excluded": len(excluded),
        "exposure": exposure,
        "notes": ds.notes,
        "next": f"lightstage run {work.root / 'import.yaml'} --from split",
        "seconds": round(time.perf_counter() - t0, 3),
    }
    write_json_atomic(work.report("import"), summary)
    return summary


def load_json(path: Path) -> Any:
    """A JSON file, or one error line naming it."""
    try:
        return json.loads(Path(path).read_text())
    except FileNotFoundError:
        raise LightstageError(f"{path}: missing") from None
    except OSError as e:
        raise LightstageError(f"{path}: unreadable ({e.strerror})") from None
    except json.JSONDecodeError as e:
        raise LightstageError(f"{path}: invalid JSON ({e})") from None
