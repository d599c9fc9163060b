"""The Python entry points a notebook uses, in one module, taking plain paths (docs/python-api.md):

```python
from lightstage.pipelines import api

rgb, saturated = api.read_frame("demo-work", "000", "cam00", 5)  # a processed OLAT frame (linear HDR)
model = api.load_model("demo-work")                               # the trained model, eval mode
hdr = api.render("demo-work", camera="000/cam00", light="000/5", model=model)
sky = api.relight("demo-work", envmap="sky.exr", camera="orbit:az=30", lights=64, model=model)
png = api.tonemap(hdr, model.exposure)                             # uint8 sRGB for display
```

Each function resolves the work directory once and calls the stage code the CLI calls, so a notebook and
`lightstage render` / `lightstage relight` give the same pixels.
"""

from __future__ import annotations

import os
from typing import Any

import numpy as np

from lightstage.workdir import WorkDir

PathLike = str | os.PathLike[str]


def work_dir(work: PathLike | WorkDir) -> WorkDir:
    """The WorkDir of a path (or the WorkDir itself): every file the pipeline writes, by name."""
    return work if isinstance(work, WorkDir) else WorkDir.at(work)


def read_frame(
    work: PathLike | WorkDir, group: str, camera: str, light: int
) -> tuple[np.ndarray, np.ndarray]:
    """A processed OLAT frame: (H, W, 3) float32 linear HDR and (H, W) bool saturation flags."""
    from lightstage.ids import FrameId
    from lightstage.records.processed import read_processed

    return read_processed(work_dir(work).frame(FrameId(group, camera, int(light))))


def read_mask(work: PathLike | WorkDir, group: str, camera: str) -> np.ndarray:
    """A view's foreground mask at the processed resolution, (H, W) bool."""
    from lightstage.ids import ViewId
    from lightstage.records.processed import read_mask as read_mask_png

    return read_mask_png(work_dir(work).mask(ViewId(group, camera)))


def calibration(work: PathLike | WorkDir) -> Any:
    """The calibration record of a work directory (lightstage.records.calibration.Calibration)."""
    from lightstage.records.calibration import Calibration

    return Calibration.load(work_dir(work).calibration)


def load_model(work: PathLike | WorkDir, checkpoint: PathLike | None = None, device: str = "cpu") -> Any:
    """The trained model of WORK (its latest checkpoint, or `checkpoint`) on `device`, in eval mode."""
    from lightstage.training.inference import load_trained

    return load_trained(work_dir(work), checkpoint, device)


def render(
    work: PathLike | WorkDir, camera: str, light: str, model: Any = None, downscale: int = 1
) -> np.ndarray:
    """(H, W, 3) float32 linear HDR of `camera` under one light, with `lightstage render`'s specs: camera
    `GROUP/CAMERA`, `orbit:az=,elev=,dist=,fov=,size=WxH` or `K=...;R=...;t=...;size=WxH`; light
    `GROUP/INDEX` (a calibrated stage light), `dir:x,y,z`, `azel:AZ,ELEV` or `pos:x,y,z[,I]`."""
    from lightstage.training.view_specs import downscale_camera, load_scene_info, parse_camera, parse_light

    w = work_dir(work)
    model = model if model is not None else load_model(w)
    scene = load_scene_info(w)
    cam = parse_camera(camera, scene, model).camera
    if downscale > 1:
        cam = downscale_camera(cam, downscale)
    query = parse_light(light, scene)
    return (np.asarray(model.image_from_camera(cam, query.direction), np.float32) * query.scale).astype(
        np.float32
    )


def relight(
    work: PathLike | WorkDir,
    envmap: PathLike,
    camera: str,
    lights: int | str = 64,
    rotate_deg: float = 0.0,
    resolution: str = "32x16",
    model: Any = None,
    downscale: int = 1,
) -> np.ndarray:
    """(H, W, 3) float32 linear HDR of `camera` relit by a lat-long HDR envmap: `lights` median-cut regions
    (or 'all' pixels) of the map at `resolution`, rotated by `rotate_deg` about +z, as `lightstage relight`."""
    from lightstage.training.envmap import envmap_lights, load_envmap, parse_resolution
    from lightstage.training.relight import relight_image
    from lightstage.training.view_specs import downscale_camera, load_scene_info, parse_camera

    w = work_dir(work)
    model = model if model is not None else load_model(w)
    scene = load_scene_info(w)
    env = load_envmap(envmap, parse_resolution(resolution), rotate_deg)
    cam = parse_camera(camera, scene, model).camera
    if downscale > 1:
        cam = downscale_camera(cam, downscale)
    return relight_image(model, cam, envmap_lights(env, lights), scene.olat_factor)


def tonemap(hdr: np.ndarray, exposure: float = 1.0) -> np.ndarray:
    """uint8 sRGB of linear HDR at `exposure` (the tonemap of every preview and metric)."""
    from lightstage.tonemap import tonemap_u8

    return tonemap_u8(hdr, exposure)
