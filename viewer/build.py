"""Build the viewer bundle of a work directory: per view of the ring a compressed OLAT basis (captured frames
and/or a trained model's renders), the basis lights' triangulation, the envmaps' weight tables (one row per
degree of rotation, from lightstage.training.light_basis), and the static page. Layout (docs/viewer.md):

```
BUNDLE/index.html, viewer.js, viewer.css      the page (no build step, no network)
BUNDLE/manifest.json                          sets, views, bases, envmaps, how it was built
BUNDLE/data/<set>/<view>.bin                  (k, h, w, 3) float16 components of one view's basis
BUNDLE/data/<set>/basis<b>_<envmap>.bin       (360, L, 3) float32 envmap weights per degree of rotation
BUNDLE/env/<envmap>.bin, <envmap>.png         (H, W, 3) float32 resampled radiance and its preview
```
"""

from __future__ import annotations

import json
import os
import shutil
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from lightstage.config import load
from lightstage.errors import LightstageError
from lightstage.viewer.display import Budget, reserved_bytes
from lightstage.viewer.sets import ROTATION_STEPS, capture_set, model_set, write_envmaps
from lightstage.workdir import WorkDir

FORMAT_VERSION = 2  # 2: display size, byte budget, progressive loading
STATIC = Path(__file__).resolve().parent / "static"
STATIC_FILES = ("index.html", "viewer.js", "viewer.css")
SOURCES = ("auto", "capture", "model", "both")


@dataclass
class ViewerConfig:
    """Options of `lightstage view` (docs/viewer.md)."""

    source: str = "auto"  # capture | model | both | auto (both where WORK has them)
    camera: str | None = None  # camera of the view ring (default: the median-elevation camera)
    views: int = 0  # calibrated views in the ring, spread over the turntable (0: one per group)
    novel: int = 1  # novel model views between consecutive ring views
    basis_lights: int = 64  # stage lights of the model basis
    capture_lights: int = 0  # most captured lights per view (0: every frame; a spread subset otherwise)
    tolerance: float = 0.03  # relative Frobenius error of each view's compressed basis (linear HDR)
    max_components: int = 64
    envmaps: list[str] = field(default_factory=list)  # the user's lat-long HDR maps (the sky is built in)
    envmap_resolution: str = "32x16"
    orbit_views: int = 12  # model ring without a calibration
    orbit_size: str = "256x192"
    checkpoint: str | None = None
    device: str = "cpu"
    light_distance: float | None = None
    light_intensity: float = 1.0
    display_size: int = 512  # longest side of every view in pixels (area-downscaled; 0: as processed)
    bundle_mb: float = 300.0  # the bundle's bound in MB (1e6 bytes): each view's components get a share of it

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> ViewerConfig:
        """The strict loader (`lightstage.config`)."""
        return load(cls, d)

    def __post_init__(self) -> None:
        if self.source not in SOURCES:
            raise LightstageError(f"--source must be one of {', '.join(SOURCES)}, got {self.source!r}")
        if not 0 <= self.tolerance < 1:
            raise LightstageError(f"--tolerance must be in [0, 1), got {self.tolerance}")
        if self.basis_lights < 1 or self.max_components < 1 or self.orbit_views < 1:
            raise LightstageError("--basis-lights, --max-components and --orbit-views must be >= 1")
        if self.views < 0 or self.novel < 0 or self.capture_lights < 0 or self.display_size < 0:
            raise LightstageError("--views, --novel, --capture-lights and --display-size must be >= 0")
        if not self.bundle_mb > 0:
            raise LightstageError(f"--bundle-mb must be > 0, got {self.bundle_mb}")


def build_key(work: WorkDir, config: ViewerConfig) -> dict[str, Any]:
    """What a bundle depends on: the options and the identity (size, mtime) of the inputs it reads."""

    def stamp(path: Path) -> list[int] | None:
        try:
            st = path.stat()
        except OSError:
            return None
        return [st.st_size, st.st_mtime_ns]

    ckpt = Path(config.checkpoint) if config.checkpoint else work.train_dir / "checkpoint.pt"
    inputs = {"checkpoint": stamp(ckpt), "calibration": stamp(work.calibration)}
    inputs.update({f"envmap:{p}": stamp(Path(p)) for p in config.envmaps})
    options = {k: v for k, v in asdict(config).items() if k != "device"}  # where it ran changes nothing
    return {"format": FORMAT_VERSION, "config": options, "inputs": inputs}


def is_current(bundle: Path, key: dict[str, Any]) -> bool:
    """Does `bundle` hold a complete viewer built with `key`?"""
    try:
        manifest = json.loads((bundle / "manifest.json").read_text())
    except (OSError, ValueError):
        return False
    return manifest.get("build", {}).get("key") == json.loads(json.dumps(key)) and all(
        (bundle / f).is_file() for f in STATIC_FILES
    )


def available_sources(work: WorkDir, config: ViewerConfig) -> list[str]:
    """The sources to build: `config.source`, or for auto those WORK has (frames + calibration, checkpoint)."""
    has_capture = work.calibration.is_file() and (work.preprocess_dir / "frames").is_dir()
    ckpt = Path(config.checkpoint) if config.checkpoint else work.train_dir / "checkpoint.pt"
    has_model = ckpt.is_file()
    if config.source == "capture" or config.source == "both":
        if not has_capture:
            raise LightstageError(
                f"{work.root}: no processed frames with a calibration (run lightstage preprocess and calibrate)"
            )
    if config.source == "model" or config.source == "both":
        if not has_model:
            raise LightstageError(f"{ckpt}: no trained checkpoint (run lightstage train)")
    if config.source == "auto":
        found = (["capture"] if has_capture else []) + (["model"] if has_model else [])
        if not found:
            raise LightstageError(
                f"{work.root}: nothing to view (neither processed frames with a calibration nor {ckpt})"
            )
        return found
    return ["capture", "model"] if config.source == "both" else [config.source]


def load_envmaps(config: ViewerConfig) -> list[tuple[str, Any]]:
    """[(name, EnvMap)]: the built-in sky first, then the user's maps (resampled to the configured size)."""
    from lightstage.training.envmap import EnvMap, load_envmap, parse_resolution, procedural_sky, resample

    w, h = parse_resolution(config.envmap_resolution)
    out = [("sky", EnvMap(resample(procedural_sky(64, 32), w, h)))]
    for path in config.envmaps:
        name = "".join(c if c.isalnum() or c in "-_" else "_" for c in Path(path).stem) or "envmap"
        while name in {n for n, _ in out}:
            name += "_"
        out.append((name, load_envmap(path, (w, h))))
    return out


def build_viewer(
    work: WorkDir,
    config: ViewerConfig,
    bundle: Path,
    progress: bool = True,
    model: Any = None,
) -> dict[str, Any]:
    """Write the viewer bundle into `bundle` (replaced atomically: built beside it, then renamed) and return
    its manifest. `model` overrides loading WORK's checkpoint."""
    from lightstage.training.view_specs import load_scene_info

    t_wall, t_cpu = time.perf_counter(), time.process_time()
    sources = available_sources(work, config)
    scene = load_scene_info(work, config.light_distance, config.light_intensity)
    envmaps = load_envmaps(config)
    bundle = Path(bundle)
    tmp = bundle.with_name(f".{bundle.name}.tmp-{os.getpid()}")
    _remove_stale(bundle)
    (tmp / "data").mkdir(parents=True)
    (tmp / "env").mkdir()
    try:
        return _build_into(tmp, bundle, work, config, scene, sources, envmaps, progress, model, t_wall, t_cpu)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def _remove_stale(bundle: Path) -> None:
    """Remove half-built bundles beside `bundle` left by killed builds (their process is gone) and our own."""
    for old in bundle.parent.glob(f".{bundle.name}.tmp-*") if bundle.parent.is_dir() else ():
        try:
            pid = int(old.name.rsplit("-", 1)[1])
            if pid != os.getpid():
                os.kill(pid, 0)
                continue  # a live build
        except ProcessLookupError:
            pass
        except (ValueError, PermissionError):
            continue
        shutil.rmtree(old, ignore_errors=True)


def _build_into(tmp, bundle, work, config, scene, sources, envmaps, progress, model, t_wall, t_cpu):
    """The body of `build_viewer`: the sets, envmaps and static files into `tmp`, then moved to `bundle`."""
    sets = []
    budget = plan_budget(work, scene, config, sources, envmaps)
    if "capture" in sources:
        sets.append(capture_set(work, scene, config, tmp, progress, budget))
    if "model" in sources:
        sets.append(model_set(work, scene, config, tmp, progress, budget, model))
    _link_ab(sets)
    env_entries = write_envmaps(envmaps, sets, scene.olat_factor, tmp, progress)
    for s in sets:
        s.pop("_bases", None)
    for name in STATIC_FILES:
        shutil.copyfile(STATIC / name, tmp / name)
    manifest = {
        "format_version": FORMAT_VERSION,
        "title": f"lightstage viewer: {work.root.name}",
        "work": str(work.root),
        "olat_factor": scene.olat_factor,
        "light_distance_m": scene.light_distance,
        "tonemap": "sRGB(clip(exposure * hdr, 0, 1)) (lightstage.tonemap)",
        "rotation_steps": ROTATION_STEPS,
        "sets": sets,
        "envmaps": env_entries,
    }
    manifest["build"] = {
        "key": json.loads(json.dumps(build_key(work, config))),
        "wall_seconds": round(time.perf_counter() - t_wall, 2),
        "cpu_seconds": round(time.process_time() - t_cpu, 2),
        "bytes": 0,
    }
    (tmp / "manifest.json").write_text(json.dumps(manifest))
    manifest["build"]["bytes"] = int(sum(p.stat().st_size for p in tmp.rglob("*") if p.is_file()))
    (tmp / "manifest.json").write_text(json.dumps(manifest))
    _replace(tmp, bundle)
    return manifest


def ring_lights(work: WorkDir, scene, config: ViewerConfig, sources: list[str]) -> list[list[int]]:
    """Per set to build, the basis-light count of each of its views (the plan of the byte budget)."""
    from lightstage.ids import ViewId
    from lightstage.viewer.sources import captured_lights, ring_camera, ring_groups

    calib = scene.calibration
    groups = []
    if calib is not None:
        camera = ring_camera(calib, config.camera)
        groups = ring_groups(calib, camera, config.views)
    out = []
    if "capture" in sources:
        cap = config.capture_lights or None
        out.append([min(len(captured_lights(work, ViewId(g, camera))), cap or 1 << 30) for g in groups])
    if "model" in sources:
        count = len(groups) * (1 + config.novel) if calib is not None else config.orbit_views
        out.append([config.basis_lights] * count)
    return out


def plan_budget(work: WorkDir, scene, config: ViewerConfig, sources: list[str], envmaps) -> Budget:
    """The bytes the views' components may take: `config.bundle_mb` less an upper bound of everything else."""
    lights = ring_lights(work, scene, config, sources)
    views = [n for s in lights for n in s]
    bases = (lights[0] if "capture" in sources else []) + (
        [config.basis_lights] if "model" in sources else []
    )
    env_pixels = max(e.width * e.height for _, e in envmaps)
    static = sum((STATIC / f).stat().st_size for f in STATIC_FILES)
    reserve = reserved_bytes(static, views, bases, len(envmaps), env_pixels, config.max_components)
    total = int(config.bundle_mb * 1e6)
    if total <= reserve:
        raise LightstageError(
            f"--bundle-mb {config.bundle_mb:g}: the manifest and envmap tables alone need {reserve / 1e6:.1f} "
            "MB; raise --bundle-mb or use fewer --capture-lights"
        )
    return Budget(total - reserve, len(views))


def _link_ab(sets: list[dict[str, Any]]) -> None:
    """Point each view of a calibrated view id at the capture set's view of the same id (the A/B frame)."""
    capture = next((i for i, s in enumerate(sets) if s["source"] == "capture"), None)
    if capture is None:
        return
    index = {v["view_id"]: j for j, v in enumerate(sets[capture]["views"]) if v.get("view_id")}
    for s in sets:
        for v in s["views"]:
            j = index.get(v.get("view_id"))
            v["ab"] = None if j is None else {"set": capture, "view": j}


def _replace(tmp: Path, bundle: Path) -> None:
    """Move the finished bundle into place: an older bundle (a folder with manifest.json) is replaced; any
    other existing non-empty folder is refused rather than overwritten."""
    if bundle.exists():
        if bundle.is_dir() and not any(bundle.iterdir()):
            bundle.rmdir()
        elif bundle.is_dir() and (bundle / "manifest.json").is_file():
            old = bundle.with_name(f".{bundle.name}.old-{os.getpid()}")
            bundle.rename(old)
            tmp.rename(bundle)
            shutil.rmtree(old, ignore_errors=True)
            return
        else:
            shutil.rmtree(tmp, ignore_errors=True)
            raise LightstageError(
                f"{bundle}: exists and is not a viewer bundle; choose another --export folder"
            )
    bundle.parent.mkdir(parents=True, exist_ok=True)
    tmp.rename(bundle)
