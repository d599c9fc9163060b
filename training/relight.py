"""Environment-map relighting of a trained OLAT model (paper §3, "Using environment map conditioning"):
each envmap light (a median-cut region, or every pixel) is one OLAT query at its direction (a light at
infinity); the white-light OLAT predictions are multiplied per RGB channel by the light's energy
(radiance x solid angle) times the irradiance-to-OLAT factor d^2 / I, and summed (docs/relighting.md).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from lightstage.cameras import camera_rays
from lightstage.config import load
from lightstage.errors import LightstageError
from lightstage.training.envmap import EnvMap, Lights
from lightstage.training.inference import RelightableModel, load_trained
from lightstage.training.view_specs import ModelViewOptions, write_hdr
from lightstage.workdir import WorkDir


def olat_images(
    model: RelightableModel, camera, directions: np.ndarray, batch_rays: int = 65536, on_rays=None
):
    """Yield (H, W, 3) float32 white-light OLAT images for each light direction. Small images are batched:
    several lights share one `render_rays` call (rays repeated per light); large ones are rendered in bands of
    rows (novel_views.render_bands: memory one image plus one band). `on_rays(n)` reports rays rendered."""
    import torch

    from lightstage.training.novel_views import render_bands

    h, w = camera.height, camera.width
    per_call = max(1, batch_rays // (h * w))
    if per_call == 1:
        for d in directions:
            yield render_bands(model, camera, d, on_rays, batch_rays)
        return
    o, r = camera_rays(camera)
    o_t = torch.from_numpy(o.astype(np.float32))
    r_t = torch.from_numpy(r.astype(np.float32))
    for i in range(0, len(directions), per_call):
        group = np.asarray(directions[i : i + per_call], np.float32)
        light = torch.from_numpy(np.repeat(group, h * w, axis=0))
        rgb = model.render_rays(o_t.repeat(len(group), 1), r_t.repeat(len(group), 1), light)
        rgb = torch.as_tensor(rgb).detach().float().cpu().numpy().reshape(len(group), h, w, 3)
        if on_rays is not None:
            on_rays(len(group) * h * w)
        yield from rgb


def relight_image(
    model: RelightableModel,
    camera,
    lights: Lights,
    olat_factor: float,
    progress: bool = False,
    batch_rays: int = 65536,
) -> np.ndarray:
    """(H, W, 3) float32 HDR: sum over lights of OLAT(omega_k) * rgb_k * olat_factor (zero lights skipped).
    Progress counts rays (lights x pixels), so a large image shows it within each light."""
    from tqdm import tqdm

    active = lights.nonzero()
    acc = np.zeros((camera.height, camera.width, 3), np.float64)
    bar = tqdm(
        total=len(active) * camera.height * camera.width,
        desc=f"relight ({len(active)} lights)",
        unit="ray",
        unit_scale=True,
        disable=not progress,
        leave=False,
    )
    images = olat_images(model, camera, active.directions, batch_rays, bar.update)
    for img, rgb in zip(images, active.rgb, strict=True):
        acc += img.astype(np.float64) * (np.asarray(rgb, np.float64) * olat_factor)
    bar.close()
    return acc.astype(np.float32)


def relative_l2(pred: np.ndarray, ref: np.ndarray) -> float:
    """||pred - ref|| / ||ref|| over all pixels and channels (linear HDR)."""
    den = float(np.linalg.norm(np.asarray(ref, np.float64)))
    num = float(np.linalg.norm(np.asarray(pred, np.float64) - np.asarray(ref, np.float64)))
    return num / den if den > 0 else (0.0 if num == 0 else float("inf"))


def psnr_tonemapped(pred: np.ndarray, ref: np.ndarray, exposure: float) -> float:
    """PSNR (dB) between the two images after the project tonemap at one exposure."""
    from lightstage.tonemap import tonemap

    mse = float(np.mean((tonemap(pred, exposure).astype(np.float64) - tonemap(ref, exposure)) ** 2))
    return float("inf") if mse == 0 else float(10.0 * np.log10(1.0 / mse))


def parse_lights_option(text: str | int | list) -> list[int | str]:
    """'64' / '16,64,all' / [16, 'all'] -> [16, 64, 'all']; counts must be powers of two; 'stage' is the
    viewer's basis of stage lights with its interpolated weights (lightstage.training.light_basis)."""
    items = text if isinstance(text, list) else str(text).split(",")
    out: list[int | str] = []
    for item in items:
        s = str(item).strip().lower()
        if s in ("all", "stage"):
            out.append(s)
            continue
        try:
            k = int(s)
        except ValueError:
            raise LightstageError(
                f"--lights: expected a power of two, 'all' or 'stage', got {item!r}"
            ) from None
        if k < 1 or k & (k - 1):
            raise LightstageError(f"--lights: {k} is not a power of two (median cut halves regions)")
        out.append(k)
    if not out:
        raise LightstageError("--lights: give at least one count or 'all'")
    return out


@dataclass
class RelightConfig(ModelViewOptions):
    """Options of `lightstage relight` (besides the ones it shares with `render`, ModelViewOptions; `fps` is
    the rotate-sweep video's)."""

    envmap: str = ""
    lights: str | int = "64"  # a power of two, or a comma list of powers of two and/or 'all'
    cameras: list[str] = field(default_factory=list)  # camera specs; empty: the first calibrated view
    resolution: str = "32x16"
    rotate_deg: float = 0.0
    rotate_sweep: int = 0  # frames of one full turn of the envmap about +z (first camera and count; 0 = off)
    out: str = "relight"

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> RelightConfig:
        """The strict loader (`lightstage.config`): unknown keys and wrong types name the key."""
        return load(cls, d)


def run_relight(
    work: WorkDir,
    config: RelightConfig,
    progress: bool = True,
    model: RelightableModel | None = None,
) -> dict[str, Any]:
    """Relight a trained model with an envmap for each camera and light count; EXR + PNG per image, a picture
    of the lights per count, and OUT/relight.json with timings and the K-light error vs 'all' when asked."""
    from lightstage.atomic import write_json_atomic
    from lightstage.frames import write_image
    from lightstage.tonemap import auto_exposure, tonemap_u8
    from lightstage.training.envmap import load_envmap, parse_resolution, preview_with_lights
    from lightstage.training.light_basis import stage_basis
    from lightstage.training.view_specs import downscale_camera, load_scene_info, parse_camera

    t0 = time.perf_counter()
    if not config.envmap:
        raise LightstageError("relight: --envmap is required")
    counts = parse_lights_option(config.lights)
    env = load_envmap(config.envmap, parse_resolution(config.resolution), config.rotate_deg)
    scene = load_scene_info(work, config.light_distance, config.light_intensity)
    if model is None:
        model = load_trained(work, config.checkpoint, config.device)
    specs = list(config.cameras)
    if not specs:
        specs = [_default_camera(scene)]
    cameras = _unique_names([parse_camera(s, scene, model) for s in specs])
    out = Path(config.out)
    out.mkdir(parents=True, exist_ok=True)

    basis = stage_basis(scene.calibration) if "stage" in counts else None
    light_sets: dict[str, Lights] = {}
    for k in counts:
        light_sets[str(k)] = light_set(env, k, basis)
    env_exposure = _env_exposure(env)
    for key, lights in light_sets.items():
        write_image(
            out / f"envmap_lights_{_tag(key)}.png", preview_with_lights(env, lights, exposure=env_exposure)
        )

    summary: dict[str, Any] = {
        "envmap": str(config.envmap),
        "envmap_resolution": [env.width, env.height],
        "rotate_deg": env.rotate_deg,
        "envmap_total_rgb_irradiance": env.energies().sum(axis=(0, 1)).tolist(),
        "light_distance_m": scene.light_distance,
        "light_intensity": scene.light_intensity,
        "olat_factor": scene.olat_factor,
        "tonemap": "sRGB(clip(exposure * hdr, 0, 1)) (lightstage.tonemap)",
        "views": {},
    }
    exposure = config.exposure
    for named in cameras:
        camera = downscale_camera(named.camera, config.downscale)
        images: dict[str, np.ndarray] = {}
        view: dict[str, Any] = {
            "camera": named.name,
            "resolution": [camera.width, camera.height],
            "results": {},
        }
        for key, lights in light_sets.items():
            t1 = time.perf_counter()
            img = relight_image(model, camera, lights, scene.olat_factor, progress)
            images[key] = img
            if exposure is None:
                exposure = auto_exposure(img, 99.0)
            path = out / f"{named.name}_{_tag(key)}.exr"
            write_hdr(path, img, {"lightstage_envmap": str(config.envmap), "lightstage_lights": key})
            write_image(path.with_suffix(".png"), tonemap_u8(img, exposure))
            view["results"][key] = {
                "lights": len(lights),
                "nonzero_lights": len(lights.nonzero()),
                "seconds": round(time.perf_counter() - t1, 3),
                "exr": str(path),
            }
        if "all" in images:
            ref = images["all"]
            for key, img in images.items():
                if key != "all":
                    view["results"][key]["vs_all"] = {
                        "relative_l2": relative_l2(img, ref),
                        "psnr_tonemapped_db": psnr_tonemapped(img, ref, exposure),
                    }
        summary["views"][named.name] = view
    summary["exposure"] = exposure
    if config.rotate_sweep:
        camera = downscale_camera(cameras[0].camera, config.downscale)
        summary["rotate_sweep"] = rotate_sweep(
            model,
            camera,
            env,
            counts[0],
            config.rotate_sweep,
            scene.olat_factor,
            exposure,
            out,
            config.fps,
            basis,
        )
    summary["seconds"] = round(time.perf_counter() - t0, 3)
    write_json_atomic(out / "relight.json", summary)
    return summary


def rotate_sweep(
    model: RelightableModel,
    camera,
    env: EnvMap,
    count: int | str,
    frames: int,
    olat_factor: float,
    exposure: float | None,
    out: Path,
    fps: float = 24.0,
    basis=None,
) -> dict[str, Any]:
    """The envmap turned once about +z in `frames` steps (light count `count`, one camera): OUT/sweep/
    frame_NNNN.exr + .png, an H.264 OUT/rotate_sweep.mp4 and a strip; one exposure for every frame."""
    import dataclasses

    from lightstage.frames import write_image
    from lightstage.tonemap import auto_exposure, tonemap_u8
    from lightstage.training.novel_views import ImageFiles, make_strip, write_video

    if frames < 1:
        raise LightstageError(f"--rotate-sweep must be >= 1 frames, got {frames}")
    pngs = []
    for k in range(frames):
        turned = dataclasses.replace(env, rotate_deg=env.rotate_deg + 360.0 * k / frames)
        img = relight_image(model, camera, light_set(turned, count, basis), olat_factor)
        if exposure is None:
            exposure = auto_exposure(img, 99.0)
        write_hdr(
            out / "sweep" / f"frame_{k:04d}.exr", img, {"lightstage_rotate_deg": f"{turned.rotate_deg:.6f}"}
        )
        pngs.append(out / "sweep" / f"frame_{k:04d}.png")
        write_image(pngs[-1], tonemap_u8(img, exposure))
    video = write_video(out / "rotate_sweep.mp4", ImageFiles(pngs), fps)
    write_image(out / "rotate_sweep_strip.png", make_strip(ImageFiles(pngs)))
    return {"frames": frames, "lights": str(count), "video": str(video), "fps": fps, "exposure": exposure}


def _unique_names(cameras: list) -> list:
    """Suffix repeated camera names (_2, _3, ...) so no output overwrites another."""
    from lightstage.training.view_specs import NamedCamera

    seen: dict[str, int] = {}
    out = []
    for c in cameras:
        seen[c.name] = seen.get(c.name, 0) + 1
        out.append(c if seen[c.name] == 1 else NamedCamera(f"{c.name}_{seen[c.name]}", c.camera))
    return out


def _tag(key: str) -> str:
    return key if key in ("all", "stage") else f"k{int(key):03d}"


def light_set(env: EnvMap, key: int | str, basis=None) -> Lights:
    """The lights of one `--lights` entry: median cut, every pixel ('all'), or the stage basis ('stage')."""
    from lightstage.training.envmap import envmap_lights
    from lightstage.training.light_basis import stage_basis, stage_lights

    if key == "stage":
        return stage_lights(env, basis if basis is not None else stage_basis(None))
    return envmap_lights(env, key)


def _env_exposure(env: EnvMap) -> float:
    from lightstage.tonemap import auto_exposure

    return auto_exposure(env.radiance, 95.0)


def _default_camera(scene) -> str:
    """The first calibrated view (sorted), or an orbit camera when WORK has no calibration."""
    if scene.calibration is not None and scene.calibration.views:
        return str(sorted(scene.calibration.views)[0])
    return "orbit"
