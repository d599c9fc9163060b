"""Novel views and lights from a trained model (`lightstage render`): the specs of training/view_specs.py rendered
as EXR frames, orbits around the scene centre as an H.264 MP4 (PyAV) and a PNG strip.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
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


BAND_RAYS = 65536  # rays made and rendered at a time by render_bands


def band_rays(camera: PinholeCamera, y0: int, y1: int) -> tuple[np.ndarray, np.ndarray]:
    """World rays ((y1 - y0) * W, 3) through the pixel centres of rows y0..y1 of `camera` (as camera_rays)."""
    from lightstage.cameras import pixel_centers, pixel_rays, undistort_pixels

    uv = pixel_centers(camera.width, y1 - y0) + np.array([0.0, y0])
    uv = undistort_pixels(uv, camera.K, camera.dist)
    return pixel_rays(uv, camera.K, camera.R, camera.t)


def render_bands(
    model: RelightableModel,
    camera: PinholeCamera,
    direction: np.ndarray,
    on_rays: Callable[[int], None] | None = None,
    rays_per_band: int = BAND_RAYS,
) -> np.ndarray:
    """(H, W, 3) float32 HDR image of `camera` under the unit light `direction`, a band of rows at a time: each
    band's rays are made, rendered and written into the image, so the memory beyond the image is one band's
    (the rays of a whole 2048 x 1366 view are 4 x 67 MB), and `on_rays(n)` reports each band's n rays."""
    import torch

    h, w = camera.height, camera.width
    rows = max(1, rays_per_band // w)
    out = np.empty((h, w, 3), np.float32)
    light = torch.from_numpy(np.asarray(direction, np.float32).reshape(1, 3))
    with torch.no_grad():
        for y0 in range(0, h, rows):
            y1 = min(h, y0 + rows)
            o, d = band_rays(camera, y0, y1)
            o_t, d_t = torch.from_numpy(o.astype(np.float32)), torch.from_numpy(d.astype(np.float32))
            rgb = model.render_rays(o_t, d_t, light.expand(len(o_t), 3))
            out[y0:y1] = torch.as_tensor(rgb).detach().float().cpu().numpy().reshape(y1 - y0, w, 3)
            if on_rays is not None:
                on_rays(len(o_t))
    return out


def render_image(
    model: RelightableModel,
    camera: PinholeCamera,
    light: LightQuery,
    on_rays: Callable[[int], None] | None = None,
) -> np.ndarray:
    """(H, W, 3) float32 HDR render of one camera under one light (in bands of rows, see render_bands)."""
    return render_bands(model, camera, light.direction, on_rays) * np.float32(light.scale)


class ImageFiles(Sequence):
    """Images kept on disk and read back when used (a video's frames): an orbit's memory stays one frame."""

    def __init__(self, paths: list[Path]):
        self.paths = list(paths)

    def __len__(self) -> int:
        return len(self.paths)

    def __getitem__(self, i: int) -> np.ndarray:  # type: ignore[override] - integers only
        """The uint8 RGB image of file i."""
        import cv2

        img = cv2.imread(str(self.paths[i]), cv2.IMREAD_COLOR)
        if img is None:
            raise LightstageError(f"{self.paths[i]}: cannot read the frame back")
        return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


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
    bar = tqdm(
        total=n * camera.width * camera.height,
        desc=f"render ({n} frame{'s' * (n > 1)})",
        unit="ray",
        unit_scale=True,
        disable=not progress,
        leave=False,
    )
    for k in range(n):
        cam = rotate_camera_about_z(camera, 360.0 * k / n, centre) if config.orbit else camera
        img = render_image(model, cam, light, bar.update)
        if exposure is None:
            exposure = auto_exposure(img, 99.0)
        stem = f"{named.name}_{light.name}" if not config.orbit else f"frame_{k:04d}"
        exr = out / (f"{stem}.exr" if not config.orbit else f"frames/{stem}.exr")
        write_hdr(exr, img, {"lightstage_light_direction": ",".join(f"{v:.6f}" for v in light.direction)})
        png = tonemap_u8(img, exposure)
        write_image(exr.with_suffix(".png"), png)
        outputs.append(str(exr))
        if config.orbit:
            frames.append(exr.with_suffix(".png"))
    bar.close()
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
        summary["video"] = str(write_video(out / "orbit.mp4", ImageFiles(frames), config.fps))
        strip = make_strip(ImageFiles(frames))
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


def write_video(path: Path, frames: Sequence[np.ndarray], fps: float, crf: int = 18) -> Path:
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


def make_strip(frames: Sequence[np.ndarray], count: int = 8, height: int = 160) -> np.ndarray:
    """A horizontal strip of up to `count` evenly spaced frames, each resized to `height` pixels."""
    import cv2

    idx = np.unique(np.linspace(0, len(frames) - 1, min(count, len(frames))).round().astype(int))
    tiles = []
    for i in idx:
        f = frames[i]
        w = max(1, round(f.shape[1] * height / f.shape[0]))
        tiles.append(cv2.resize(f, (w, height), interpolation=cv2.INTER_AREA))
    return np.concatenate(tiles, axis=1)
