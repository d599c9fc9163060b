"""Camera and light specs of the commands that use a trained model (`render`, `relight`): a calibrated view,
an orbit camera, explicit K/R/t or a camera JSON; a light direction, a point-light position or a calibrated
stage light. Parsed into PinholeCameras and light queries; errors name the spec and what is wrong.
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from lightstage.cameras import PinholeCamera, camera_center, look_at, rotation_z
from lightstage.errors import LightstageError
from lightstage.workdir import WorkDir

if TYPE_CHECKING:
    from lightstage.records.calibration import Calibration
    from lightstage.training.inference import RelightableModel

# Paper stage: lights on a sphere of radius 1.5 m around the scene centre (used without a calibration).
DEFAULT_LIGHT_DISTANCE = 1.5


@dataclass
class ModelViewOptions:
    """The options `render` and `relight` share: video frame rate, output downscale and exposure, which
    checkpoint on which device, and the capture's light distance and intensity (docs/relighting.md)."""

    fps: float = 24.0
    downscale: int = 1
    exposure: float | None = None
    checkpoint: str | None = None
    device: str = "cpu"
    light_distance: float | None = None
    light_intensity: float = 1.0


@dataclass(frozen=True)
class SceneInfo:
    """What camera and light specs need besides the model: the calibration (if any), the centre that light
    directions are measured from, and the capture's light distance and intensity (docs/relighting.md)."""

    calibration: Calibration | None
    scene_centre: np.ndarray
    light_distance: float
    light_intensity: float = 1.0

    @property
    def olat_factor(self) -> float:
        """Irradiance-to-OLAT factor: an envmap light of energy E (= L x Omega) is E * d^2 / I OLAT images."""
        return self.light_distance**2 / self.light_intensity


def load_scene_info(
    work: WorkDir, light_distance: float | None = None, light_intensity: float = 1.0
) -> SceneInfo:
    """Calibration (when WORK has one), scene centre and light distance (the median calibrated light
    distance from the scene centre unless given; 1.5 m, the paper stage's radius, without a calibration)."""
    from lightstage.records.calibration import Calibration

    calib = Calibration.load(work.calibration) if work.calibration.is_file() else None
    centre = np.asarray(calib.scene_centre, np.float64) if calib is not None else np.zeros(3)
    if light_distance is None:
        if calib is not None and calib.light_positions:
            pos = np.concatenate(
                [np.asarray(p, np.float64).reshape(-1, 3) for p in calib.light_positions.values()]
            )
            light_distance = float(np.median(np.linalg.norm(pos - centre, axis=1)))
        else:
            light_distance = DEFAULT_LIGHT_DISTANCE
    if not light_distance > 0 or not light_intensity > 0:
        raise LightstageError(
            f"light distance and intensity must be positive, got {light_distance} and {light_intensity}"
        )
    return SceneInfo(calib, centre, float(light_distance), float(light_intensity))


# ----------------------------------------------------------------------------------------------- cameras


@dataclass(frozen=True)
class NamedCamera:
    """A camera with a file-name-safe label for its outputs."""

    name: str
    camera: PinholeCamera


def _numbers(text: str, count: int | None, what: str) -> list[float]:
    try:
        vals = [float(v) for v in text.split(",") if v.strip() != ""]
    except ValueError:
        raise LightstageError(f"{what}: expected comma-separated numbers, got {text!r}") from None
    if count is not None and len(vals) != count:
        raise LightstageError(f"{what}: expected {count} numbers, got {len(vals)} in {text!r}")
    return vals


def _size(text: str, what: str) -> tuple[int, int]:
    m = re.fullmatch(r"\s*(\d+)\s*x\s*(\d+)\s*", text)
    if not m or int(m.group(1)) < 1 or int(m.group(2)) < 1:
        raise LightstageError(f"{what}: size must look like 640x480, got {text!r}")
    return int(m.group(1)), int(m.group(2))


def _keyvals(text: str, allowed: set[str], what: str, sep: str = ",") -> dict[str, str]:
    out: dict[str, str] = {}
    for part in filter(None, (p.strip() for p in text.split(sep))):
        if "=" not in part:
            raise LightstageError(f"{what}: expected key=value, got {part!r}")
        k, v = (s.strip() for s in part.split("=", 1))
        if k not in allowed:
            raise LightstageError(f"{what}: unknown key {k!r} (allowed: {', '.join(sorted(allowed))})")
        out[k] = v
    return out


def orbit_camera(
    centre: np.ndarray,
    azimuth_deg: float,
    elevation_deg: float,
    distance: float,
    fov_deg: float = 40.0,
    size: tuple[int, int] = (512, 384),
) -> PinholeCamera:
    """A camera `distance` from `centre` at azimuth (from +x towards +y) / elevation, looking at the centre
    with +z up and a horizontal field of view `fov_deg`."""
    if not distance > 0 or not 0 < fov_deg < 180:
        raise LightstageError(f"orbit camera: need distance > 0 and 0 < fov < 180, got {distance}, {fov_deg}")
    az, el = np.deg2rad(azimuth_deg), np.deg2rad(elevation_deg)
    c = np.asarray(centre, np.float64)
    pos = c + distance * np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
    R, t = look_at(pos, c)
    w, h = size
    f = 0.5 * w / np.tan(np.deg2rad(fov_deg) / 2)
    K = np.array([[f, 0.0, w / 2], [0.0, f, h / 2], [0.0, 0.0, 1.0]])
    return PinholeCamera(K, R, t, w, h)


def rotate_camera_about_z(camera: PinholeCamera, angle_deg: float, centre: np.ndarray) -> PinholeCamera:
    """The camera carried around the vertical (+z) axis through `centre` by `angle_deg` (right-handed)."""
    Rz = rotation_z(np.deg2rad(angle_deg))
    c = np.asarray(centre, np.float64)
    C = c + Rz @ (camera_center(camera.R, camera.t) - c)
    R = np.asarray(camera.R) @ Rz.T
    return PinholeCamera(camera.K, R, -R @ C, camera.width, camera.height, camera.dist)


def downscale_camera(camera: PinholeCamera, factor: int) -> PinholeCamera:
    """The camera at 1/factor resolution (intrinsics scaled by 1/factor; size floored when not divisible)."""
    if factor == 1:
        return camera
    if factor < 1:
        raise LightstageError(f"image downscale must be a positive integer, got {factor}")
    from lightstage.cameras import scale_intrinsics

    w, h = camera.width // factor, camera.height // factor
    if w < 1 or h < 1:
        raise LightstageError(
            f"downscale {factor} leaves no pixels of a {camera.width}x{camera.height} camera"
        )
    return PinholeCamera(scale_intrinsics(camera.K, 1.0 / factor), camera.R, camera.t, w, h, camera.dist)


def parse_camera(spec: str, scene: SceneInfo, model: RelightableModel) -> NamedCamera:
    """A camera from a spec:
    `GROUP/CAMERA` (a calibrated view at processed resolution, e.g. `000/cam03`);
    `orbit[:az=DEG,elev=DEG,dist=M,fov=DEG,size=WxH]` (looking at the scene-bounds centre);
    `K=fx,fy,cx,cy;R=r11,...,r33;t=t1,t2,t3;size=WxH` (explicit OpenCV world-to-camera pose);
    or a JSON file with K (3x3), R (3x3), t (3), width, height and optional dist."""
    spec = spec.strip()
    if spec.endswith(".json"):
        return _json_camera(Path(spec))
    if re.fullmatch(r"[^/\s:;=]+/[^/\s:;=]+", spec):
        return _calibrated_camera(spec, scene)
    if spec == "orbit" or spec.startswith("orbit:"):
        return _orbit_spec(spec, model)
    if spec.startswith("K="):
        return _explicit_camera(spec)
    raise LightstageError(
        f"camera spec {spec!r}: expected GROUP/CAMERA, orbit[:az=..,elev=..,dist=..,fov=..,size=WxH], "
        "K=..;R=..;t=..;size=WxH, or a .json file"
    )


def _calibrated_camera(spec: str, scene: SceneInfo) -> NamedCamera:
    from lightstage.ids import ViewId

    if scene.calibration is None:
        raise LightstageError(
            f"camera {spec!r}: the work directory has no calibration (run `lightstage calibrate`)"
        )
    group, cam = spec.split("/")
    view = ViewId(group, cam)
    if view not in scene.calibration.views:
        known = ", ".join(str(v) for v in sorted(scene.calibration.views)[:5])
        raise LightstageError(f"camera {spec!r}: no such calibrated view (e.g. {known})")
    return NamedCamera(f"{group}_{cam}", scene.calibration.views[view].camera())


def _orbit_spec(spec: str, model: RelightableModel) -> NamedCamera:
    kv = _keyvals(spec[6:], {"az", "elev", "dist", "fov", "size"}, f"camera {spec!r}")
    try:
        az = float(kv.get("az", 0.0))
        el = float(kv.get("elev", 20.0))
        fov = float(kv.get("fov", 40.0))
        dist = float(kv["dist"]) if "dist" in kv else None
    except ValueError:
        raise LightstageError(f"camera {spec!r}: az, elev, dist and fov must be numbers") from None
    size = _size(kv["size"], f"camera {spec!r}") if "size" in kv else (512, 384)
    centre = np.broadcast_to(np.asarray(model.centre, np.float64), (3,))
    if dist is None:  # fit the bounding cube's circumscribed sphere into the field of view
        radius = float(np.linalg.norm(np.broadcast_to(np.asarray(model.scale, np.float64), (3,))))
        dist = 1.05 * radius / np.sin(np.deg2rad(min(fov, 179.0)) / 2 * min(1.0, size[1] / size[0]))
    name = f"orbit_az{az:g}_el{el:g}".replace("-", "m").replace(".", "p")
    return NamedCamera(name, orbit_camera(centre, az, el, dist, fov, size))


def _explicit_camera(spec: str) -> NamedCamera:
    kv = _keyvals(spec, {"K", "R", "t", "size"}, f"camera {spec!r}", sep=";")
    missing = {"K", "R", "t", "size"} - set(kv)
    if missing:
        raise LightstageError(f"camera {spec!r}: missing {', '.join(sorted(missing))}")
    fx, fy, cx, cy = _numbers(kv["K"], 4, "camera K")
    K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    R = np.array(_numbers(kv["R"], 9, "camera R")).reshape(3, 3)
    t = np.array(_numbers(kv["t"], 3, "camera t"))
    w, h = _size(kv["size"], "camera size")
    return NamedCamera("explicit", _checked_camera(K, R, t, w, h, None, f"camera {spec!r}"))


def _json_camera(path: Path) -> NamedCamera:
    try:
        d = json.loads(path.read_text())
        K, R, t = np.array(d["K"], float), np.array(d["R"], float), np.array(d["t"], float).reshape(3)
        w, h = int(d["width"]), int(d["height"])
        dist = np.array(d["dist"], float) if "dist" in d else None
    except OSError as e:
        raise LightstageError(f"{path}: cannot read camera file ({e.strerror})") from None
    except (KeyError, TypeError, ValueError) as e:
        raise LightstageError(
            f"{path}: camera file needs K (3x3), R (3x3), t (3), width, height ({type(e).__name__}: {e})"
        ) from None
    return NamedCamera(path.stem, _checked_camera(K, R, t, w, h, dist, str(path)))


def _checked_camera(K, R, t, w, h, dist, what: str) -> PinholeCamera:
    if K.shape != (3, 3) or R.shape != (3, 3) or w < 1 or h < 1:
        raise LightstageError(f"{what}: K and R must be 3x3 and the size positive")
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-5) or np.linalg.det(R) < 0:
        raise LightstageError(f"{what}: R is not a rotation matrix")
    if not (K[0, 0] > 0 and K[1, 1] > 0):
        raise LightstageError(f"{what}: focal lengths must be positive")
    return PinholeCamera(K, R, t, w, h, np.zeros(5) if dist is None else dist)


# ------------------------------------------------------------------------------------------------ lights


@dataclass(frozen=True)
class LightQuery:
    """One OLAT query: unit direction omega (from the scene centre towards the light) and the factor that
    multiplies the model's OLAT prediction (1 = the capture's own point light at the capture distance)."""

    name: str
    direction: np.ndarray
    scale: float = 1.0


def parse_light(spec: str, scene: SceneInfo) -> LightQuery:
    """A light from a spec:
    `dir:x,y,z` (a direction at infinity, as bright as a capture light);
    `azel:AZ,ELEV` (degrees; azimuth from +x towards +y);
    `pos:x,y,z[,INTENSITY]` (a point light in metres; scaled by INTENSITY d^2 / (I r^2), inverse square);
    `GROUP/INDEX` (calibrated stage light, 0-based, e.g. `000/42`: exactly the capture's OLAT)."""
    spec = spec.strip()
    what = f"light {spec!r}"
    if spec.startswith("dir:"):
        d = np.array(_numbers(spec[4:], 3, what))
        return LightQuery("dir", _unit(d, what))
    if spec.startswith("azel:"):
        az, el = np.deg2rad(_numbers(spec[5:], 2, what))
        return LightQuery("azel", np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)]))
    if spec.startswith("pos:"):
        vals = _numbers(spec[4:], None, what)
        if len(vals) not in (3, 4):
            raise LightstageError(f"{what}: expected x,y,z or x,y,z,intensity")
        intensity = vals[3] if len(vals) == 4 else scene.light_intensity
        rel = np.array(vals[:3]) - scene.scene_centre
        r = float(np.linalg.norm(rel))
        scale = intensity * scene.light_distance**2 / (scene.light_intensity * r**2) if r > 0 else 0.0
        return LightQuery("pos", _unit(rel, what), scale)
    m = re.fullmatch(r"([^/\s]+)/(\d+)", spec)
    if m:
        if scene.calibration is None:
            raise LightstageError(f"{what}: the work directory has no calibration")
        group, index = m.group(1), int(m.group(2))
        pos = scene.calibration.light_positions.get(group)
        if pos is None or not 0 <= index < len(pos):
            raise LightstageError(f"{what}: no such calibrated light (group {group!r}, 0-based index)")
        from lightstage.lights import light_direction

        return LightQuery(f"light{group}_{index:03d}", light_direction(pos[index], scene.scene_centre))
    raise LightstageError(f"{what}: expected dir:x,y,z, azel:AZ,ELEV, pos:x,y,z[,I] or GROUP/INDEX")


def _unit(v: np.ndarray, what: str) -> np.ndarray:
    n = float(np.linalg.norm(v))
    if not n > 0 or not np.isfinite(n):
        raise LightstageError(f"{what}: the direction must be a non-zero finite vector")
    return np.asarray(v, np.float64) / n


# ------------------------------------------------------------------------------------------------ render


def write_hdr(path: Path, img: np.ndarray, attributes: dict[str, str] | None = None) -> None:
    """Linear HDR EXR: float16 (the project's disk format) unless a value exceeds half's range, then float32."""
    from lightstage.frames import write_exr

    half = bool(np.all(np.abs(img) < 65000.0))
    write_exr(path, img, half=half, attributes=attributes)
