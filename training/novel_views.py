"""Novel views and lights from a trained model (`lightstage render`): the specs of training/view_specs.py rendered
as EXR frames, orbits around the scene centre as an H.264 MP4 (PyAV) and a PNG strip.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from lightstage.cameras import PinholeCamera
from lightstage.config import load
from lightstage.errors import LightstageError
from lightstage.training.inference import RelightableModel
from lightstage.training.view_specs import (
    LightQuery,
    ModelViewOptions,
    downscale_camera,
    load_scene_info,
    parse_camera,
    parse_light,
    rotate_camera_about_z,
    write_hdr,
)
from lightstage.workdir import WorkDir


@dataclass
class RenderConfig(ModelViewOptions):
    """Options of `lightstage render` (besides the ones it shares with `relight`, ModelViewOptions)."""

    camera: str = "orbit"
    light: str = "dir:0,0,1"
    orbit: int = 0  # frames of a full turn about +z through the scene-bounds centre (0 = one image)
    out: str = "render"

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> RenderConfig:
        """The strict loader (`lightstage.config`): unknown keys and wrong types name the key."""
        return load(cls, d)


def render_image(model: RelightableModel, camera: PinholeCamera, light: LightQuery) -> np.ndarray:
    """(H, W, 3) float32 HDR render of one camera under one light."""
    img = np.asarray(model.image_from_camera(camera, np.asarray(light.direction, np.float32)), np.float32)
    return img * np.float32(light.scale)


def run_render(
    work: WorkDir,
    config: RenderConfig,
    client: Any = None,
    progress: bool = True,
    model: RelightableModel | None = None,
) -> dict[str, Any]:
    """Render one image (or an orbit) for a camera spec and a light spec; EXR + PNG (+ MP4 and strip)."""
    from tqdm import tqdm

    from lightstage.atomic import write_json_atomic
    from lightstage.frames import write_image
    from lightstage.tonemap import auto_exposure, tonemap_u8

    if config.orbit < 0:
        raise LightstageError(f"--orbit must be >= 0, got {config.orbit}")
    t0 = time.perf_counter()
    scene = load_scene_info(work, config.light_distance, config.light_intensity)
    if model is None:
        from lightstage.training.inference import load_trained

        model = load_trained(work, config.checkpoint, config.device)
    named = parse_camera(config.camera, scene, model)
    camera = downscale_camera(named.camera, config.downscale)
    light = parse_light(config.light, scene)
    out = Path(config.out)
    out.mkdir(parents=True, exist_ok=True)
    centre = np.broadcast_to(np.asarray(model.centre, np.float64), (3,))
    n = max(1, config.orbit)
    frames = []
    # the capture's exposure (stored with the checkpoint) when the model has one, so renders match previews
    exposure = config.exposure if config.exposure is not None else getattr(model, "exposure", None)
    outputs: list[str] = []
    for k in tqdm(range(n), desc="render", disable=not progress or n == 1):
        cam = rotate_camera_about_z(camera, 360.0 * k / n, centre) if config.orbit else camera
        img = render_image(model, cam, light)
        if exposure is None:
            exposure = auto_exposure(img, 99.0)
        stem = f"{named.name}_{light.name}" if not config.orbit else f"frame_{k:04d}"
        exr = out / (f"{stem}.exr" if not config.orbit else f"frames/{stem}.exr")
        write_hdr(exr, img, {"lightstage_light_direction": ",".join(f"{v:.6f}" for v in light.direction)})
        png = tonemap_u8(img, exposure)
        write_image(exr.with_suffix(".png"), png)
        outputs.append(str(exr))
        if config.orbit:
            frames.append(png)
    summary: dict[str, Any] = {
        "camera": config.camera,
        "light": config.light,
        "light_direction": light.direction.tolist(),
        "light_scale": light.scale,
        "resolution": [camera.width, camera.height],
        "frames": n,
        "exposure": exposure,
        "tonemap": "sRGB(clip(exposure * hdr, 0, 1)) (lightstage.tonemap)",
        "outputs": outputs[:10],
    }
    if config.orbit:
        summary["video"] = str(write_video(out / "orbit.mp4", frames, config.fps))
        strip = make_strip(frames)
        write_image(out / "orbit_strip.png", strip)
        summary["strip"] = str(out / "orbit_strip.png")
    summary["seconds"] = round(time.perf_counter() - t0, 3)
    write_json_atomic(out / "render.json", summary)
    return summary


H264_ENCODERS = ("libx264", "h264", "libopenh264")  # PyAV encoder names, first available wins


def h264_encoder() -> str:
    """The first H.264 encoder the installed PyAV (its bundled FFmpeg) offers; one clear error otherwise."""
    try:
        import av
    except ImportError:
        raise LightstageError("writing MP4 needs PyAV: pip install av") from None
    for name in H264_ENCODERS:
        try:
            av.codec.Codec(name, "w")
            return name
        except Exception:  # noqa: BLE001 - PyAV raises its own UnknownCodecError per missing encoder
            continue
    raise LightstageError(f"PyAV {av.__version__} has no H.264 encoder (tried {', '.join(H264_ENCODERS)})")


def write_video(path: Path, frames: list[np.ndarray], fps: float, crf: int = 18) -> Path:
    """Write uint8 RGB frames as an H.264 MP4 (PyAV: yuv420p, `crf` quality, moov atom first so browsers
    start playing at once) that browsers, GitHub and slide tools play; odd sizes are padded to even."""
    from fractions import Fraction

    import av

    from lightstage.atomic import atomic_path

    encoder = h264_encoder()
    h, w = frames[0].shape[:2]
    he, we = h + h % 2, w + w % 2
    with atomic_path(path) as tmp:
        with av.open(str(tmp), mode="w", format="mp4", options={"movflags": "+faststart"}) as container:
            stream = container.add_stream(encoder, rate=Fraction(fps).limit_denominator(1001))
            stream.width, stream.height, stream.pix_fmt = we, he, "yuv420p"
            stream.options = {"crf": str(crf)} if encoder != "libopenh264" else {}
            for f in frames:
                f = np.pad(np.asarray(f, np.uint8), ((0, he - h), (0, we - w), (0, 0)))
                frame = av.VideoFrame.from_ndarray(np.ascontiguousarray(f[..., :3]), format="rgb24")
                for packet in stream.encode(frame):
                    container.mux(packet)
            for packet in stream.encode():
                container.mux(packet)
    return path


def make_strip(frames: list[np.ndarray], count: int = 8, height: int = 160) -> np.ndarray:
    """A horizontal strip of up to `count` evenly spaced frames, each resized to `height` pixels."""
    import cv2

    idx = np.unique(np.linspace(0, len(frames) - 1, min(count, len(frames))).round().astype(int))
    tiles = []
    for i in idx:
        f = frames[i]
        w = max(1, round(f.shape[1] * height / f.shape[0]))
        tiles.append(cv2.resize(f, (w, height), interpolation=cv2.INTER_AREA))
    return np.concatenate(tiles, axis=1)
