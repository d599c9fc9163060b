"""The light-stage description (`stage.yaml`): cameras, lights, groups, sphere, sensor — typed and validated.

All poses and light positions here are nominal and in the rig frame (origin at the sphere centre, +z up,
metres); `lightstage.rig` maps them into the world frame per group.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from lightstage.atomic import write_text_atomic
from lightstage.cameras import PinholeCamera
from lightstage.config import check_keys, describe, read_yaml
from lightstage.errors import LightstageError
from lightstage.rig import TurntableAxis, camera_pose_in_world, light_position_in_world

STAGE_FORMAT_VERSION = 1


@dataclass(frozen=True)
class CameraSpec:
    """One rigidly mounted camera: nominal intrinsics at raw resolution and rig-frame world-to-camera pose."""

    id: str
    fx: float
    fy: float
    cx: float
    cy: float
    R: np.ndarray  # 3x3, rig frame -> camera
    t: np.ndarray  # 3
    distortion: np.ndarray | None = None  # OpenCV k1 k2 p1 p2 k3

    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])


@dataclass(frozen=True)
class LightSpec:
    """One light: 0-based index, rig-frame position in metres, relative RGB intensity.

    `intensity`: the light's emission relative to the stage's reference light, per channel (real LEDs differ
    by tens of percent and in colour; measure them, e.g. on a white target). Preprocess divides every
    processed frame by its light's intensity, so downstream stages see equal white lights.
    `directional`: a distant light known only by its direction (datasets of distant lights); `position` is
    then the point on the light sphere in that direction (sphere_radius x the unit direction), so the paper's
    light direction normalize(p - centre) is the given direction."""

    index: int
    position: np.ndarray  # 3
    intensity: tuple[float, float, float] = (1.0, 1.0, 1.0)
    directional: bool = False


@dataclass(frozen=True)
class GroupSpec:
    """One turntable position: name (three-digit yaw, e.g. '040') and yaw in degrees."""

    name: str
    yaw_deg: float


@dataclass(frozen=True)
class Stage:
    """A whole light stage. Cameras, lights and groups keep file order; index = position in the list."""

    name: str
    cameras: tuple[CameraSpec, ...]
    lights: tuple[LightSpec, ...]
    groups: tuple[GroupSpec, ...]
    width: int
    height: int
    saturation: float
    sphere_radius: float = 1.5
    centre_height: float = 1.1
    units: str = "m"
    axis: TurntableAxis = field(default_factory=TurntableAxis)

    # ---- lookups -------------------------------------------------------------------------------
    @property
    def camera_ids(self) -> list[str]:
        return [c.id for c in self.cameras]

    @property
    def group_names(self) -> list[str]:
        return [g.name for g in self.groups]

    @property
    def num_frames(self) -> int:
        return len(self.groups) * len(self.cameras) * len(self.lights)

    def camera(self, camera_id: str) -> CameraSpec:
        for c in self.cameras:
            if c.id == camera_id:
                return c
        raise LightstageError(f"stage {self.name!r} has no camera {camera_id!r}")

    def group(self, name: str) -> GroupSpec:
        for g in self.groups:
            if g.name == name:
                return g
        raise LightstageError(f"stage {self.name!r} has no group {name!r}")

    def light_positions_rig(self) -> np.ndarray:
        """(L, 3) nominal rig-frame light positions, in index order."""
        return np.stack([lt.position for lt in self.lights])

    def light_intensities(self) -> np.ndarray:
        """(L, 3) relative RGB intensities, in index order (all 1 unless stage.yaml gives them)."""
        return np.array([lt.intensity for lt in self.lights], np.float64).reshape(len(self.lights), 3)

    @property
    def equal_lights(self) -> bool:
        """Every light has intensity (1, 1, 1)."""
        return bool(np.all(self.light_intensities() == 1.0))

    # ---- nominal world geometry ------------------------------------------------------------------
    def view_camera(self, group: str, camera_id: str) -> PinholeCamera:
        """Nominal world-frame camera of a view (group, camera) at raw resolution."""
        cam = self.camera(camera_id)
        R, t = camera_pose_in_world(cam.R, cam.t, self.group(group).yaw_deg, self.axis)
        dist = cam.distortion if cam.distortion is not None else np.zeros(5)
        return PinholeCamera(cam.K, R, t, self.width, self.height, dist)

    def light_positions_world(self, group: str) -> np.ndarray:
        """(L, 3) nominal world light positions for a group (lights turn with the rig)."""
        return light_position_in_world(self.light_positions_rig(), self.group(group).yaw_deg, self.axis)

    # ---- (de)serialisation -----------------------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        def cam(c: CameraSpec) -> dict[str, Any]:
            d: dict[str, Any] = {
                "id": c.id,
                "intrinsics": {"fx": float(c.fx), "fy": float(c.fy), "cx": float(c.cx), "cy": float(c.cy)},
                "pose": {"R": np.asarray(c.R, float).tolist(), "t": np.asarray(c.t, float).tolist()},
            }
            if c.distortion is not None:
                d["distortion"] = np.asarray(c.distortion, float).tolist()
            return d

        return {
            "format_version": STAGE_FORMAT_VERSION,
            "name": self.name,
            "units": self.units,
            "sphere_radius": float(self.sphere_radius),
            "centre_height": float(self.centre_height),
            "resolution": {"width": int(self.width), "height": int(self.height)},
            "saturation": float(self.saturation),
            "turntable_axis": {
                "direction": np.asarray(self.axis.direction, float).tolist(),
                "point": np.asarray(self.axis.point, float).tolist(),
            },
            "groups": [{"name": g.name, "yaw_deg": float(g.yaw_deg)} for g in self.groups],
            "cameras": [cam(c) for c in self.cameras],
            "lights": [_light_dict(lt, self.sphere_radius) for lt in self.lights],
        }

    def save(self, path: str | os.PathLike[str]) -> None:
        """Write as YAML (atomically)."""
        write_text_atomic(path, yaml.safe_dump(self.to_dict(), sort_keys=False, default_flow_style=None))


def _light_dict(lt: LightSpec, sphere_radius: float) -> dict[str, Any]:
    d: dict[str, Any] = {"index": int(lt.index)}
    if lt.directional:
        p = np.asarray(lt.position, float)
        d["direction"] = (p / np.linalg.norm(p)).tolist()
    else:
        d["position"] = np.asarray(lt.position, float).tolist()
    if tuple(lt.intensity) != (1.0, 1.0, 1.0):
        d["intensity"] = [float(x) for x in lt.intensity]
    return d


# ---- loading and validation ----------------------------------------------------------------------
class _Reader:
    """Typed access to a parsed YAML mapping; every error names the file and the field."""

    def __init__(self, source: str):
        self.source = source

    def fail(self, field_name: str, problem: str) -> LightstageError:
        return LightstageError(f"{self.source}: {field_name}: {problem}")

    def get(self, d: Any, key: str, where: str, kind: type | tuple[type, ...], default: Any = ...) -> Any:
        name = f"{where}.{key}" if where else key
        if not isinstance(d, dict):
            raise self.fail(where or "<top>", "expected a mapping")
        if key not in d:
            if default is ...:
                raise self.fail(name, "missing")
            return default
        value = d[key]
        if kind is float and isinstance(value, int) and not isinstance(value, bool):
            value = float(value)
        if not isinstance(value, kind) or isinstance(value, bool) and kind is not bool:
            raise self.fail(name, f"expected {describe(kind)}, got {value!r}")
        return value

    def keys(self, d: Any, known: tuple[str, ...], *where: str | int) -> None:
        """Reject a key of mapping `d` (at `where`) that stage.yaml does not have, suggesting the closest."""
        if isinstance(d, dict):
            check_keys(d, known, where, self.source)

    def array(self, d: Any, key: str, where: str, shape: tuple[int, ...], default: Any = ...) -> np.ndarray:
        value = self.get(d, key, where, list, default)
        if value is None:
            return None
        name = f"{where}.{key}"
        try:
            arr = np.asarray(value, dtype=np.float64)
        except (TypeError, ValueError):
            raise self.fail(name, f"expected numbers of shape {shape}") from None
        if arr.shape != shape:
            raise self.fail(name, f"expected shape {shape}, got {arr.shape}")
        if not np.all(np.isfinite(arr)):
            raise self.fail(name, "contains non-finite values")
        return arr


_TOP_KEYS = (
    "format_version",
    "name",
    "units",
    "sphere_radius",
    "centre_height",
    "resolution",
    "saturation",
    "turntable_axis",
    "groups",
    "cameras",
    "lights",
)


def stage_from_dict(data: Any, source: str = "stage.yaml") -> Stage:
    """Build and validate a Stage from a parsed YAML mapping; a key stage.yaml does not have is an error
    suggesting the closest one (`stage.yaml: unknown key 'sphere_radus' (did you mean 'sphere_radius'?)`)."""
    r = _Reader(source)
    if not isinstance(data, dict):
        raise r.fail("<top>", "expected a mapping")
    version = r.get(data, "format_version", "", int, STAGE_FORMAT_VERSION)
    if version != STAGE_FORMAT_VERSION:
        raise r.fail(
            "format_version", f"unsupported version {version} (this lightstage reads {STAGE_FORMAT_VERSION})"
        )
    r.keys(data, _TOP_KEYS)
    res = r.get(data, "resolution", "", dict)
    r.keys(res, ("width", "height"), "resolution")
    axis = r.get(data, "turntable_axis", "", dict, {})
    r.keys(axis, ("direction", "point"), "turntable_axis")
    cameras = []
    for i, c in enumerate(r.get(data, "cameras", "", list)):
        where = f"cameras[{i}]"
        r.keys(c, ("id", "intrinsics", "pose", "distortion"), "cameras", i)
        intr = r.get(c, "intrinsics", where, dict)
        r.keys(intr, ("fx", "fy", "cx", "cy"), "cameras", i, "intrinsics")
        pose = r.get(c, "pose", where, dict)
        r.keys(pose, ("R", "t"), "cameras", i, "pose")
        cameras.append(
            CameraSpec(
                id=r.get(c, "id", where, str),
                fx=r.get(intr, "fx", where + ".intrinsics", float),
                fy=r.get(intr, "fy", where + ".intrinsics", float),
                cx=r.get(intr, "cx", where + ".intrinsics", float),
                cy=r.get(intr, "cy", where + ".intrinsics", float),
                R=r.array(pose, "R", where + ".pose", (3, 3)),
                t=r.array(pose, "t", where + ".pose", (3,)),
                distortion=r.array(c, "distortion", where, (5,), None),
            )
        )
    sphere_radius = r.get(data, "sphere_radius", "", float, 1.5)
    lights = []
    for i, lt in enumerate(r.get(data, "lights", "", list)):
        where = f"lights[{i}]"
        r.keys(lt, ("index", "position", "direction", "intensity"), "lights", i)
        index = r.get(lt, "index", where, int)
        if isinstance(lt, dict) and "direction" in lt:
            if "position" in lt:
                raise r.fail(where, "give either position (a point light) or direction (a distant light)")
            direction = r.array(lt, "direction", where, (3,))
            norm = float(np.linalg.norm(direction))
            if not norm > 0:
                raise r.fail(where + ".direction", "must be a non-zero vector")
            position, directional = direction / norm * sphere_radius, True
        else:
            position, directional = r.array(lt, "position", where, (3,)), False
        intensity = r.array(lt, "intensity", where, (3,), None)
        if intensity is None:
            intensity = np.ones(3)
        if not np.all(intensity > 0):
            raise r.fail(where + ".intensity", f"must be positive (relative RGB), got {intensity.tolist()}")
        lights.append(LightSpec(index, position, tuple(float(x) for x in intensity), directional))
    groups = []
    for i, g in enumerate(r.get(data, "groups", "", list)):
        where = f"groups[{i}]"
        r.keys(g, ("name", "yaw_deg"), "groups", i)
        groups.append(GroupSpec(r.get(g, "name", where, str), r.get(g, "yaw_deg", where, float)))
    stage = Stage(
        name=str(r.get(data, "name", "", str, "stage")),
        cameras=tuple(cameras),
        lights=tuple(lights),
        groups=tuple(groups),
        width=r.get(res, "width", "resolution", int),
        height=r.get(res, "height", "resolution", int),
        saturation=r.get(data, "saturation", "", float),
        sphere_radius=sphere_radius,
        centre_height=r.get(data, "centre_height", "", float, 1.1),
        units=r.get(data, "units", "", str, "m"),
        axis=TurntableAxis(
            tuple(r.array(axis, "direction", "turntable_axis", (3,), [0.0, 0.0, 1.0])),
            tuple(r.array(axis, "point", "turntable_axis", (3,), [0.0, 0.0, 0.0])),
        ),
    )
    validate_stage(stage, source)
    return stage


def validate_stage(stage: Stage, source: str = "stage") -> None:
    """Raise LightstageError naming the field for any inconsistency in the stage description."""
    r = _Reader(source)
    if stage.units != "m":
        raise r.fail("units", f"only metres ('m') are supported, got {stage.units!r}")
    if stage.width <= 0 or stage.height <= 0:
        raise r.fail("resolution", f"must be positive, got {stage.width}x{stage.height}")
    if not stage.saturation > 0:
        raise r.fail("saturation", f"must be positive, got {stage.saturation}")
    if not stage.sphere_radius > 0:
        raise r.fail("sphere_radius", f"must be positive, got {stage.sphere_radius}")
    if not stage.centre_height > 0:
        raise r.fail("centre_height", f"must be positive, got {stage.centre_height}")
    for name, items in (("cameras", stage.cameras), ("lights", stage.lights), ("groups", stage.groups)):
        if not items:
            raise r.fail(name, "must not be empty")
    _no_duplicates(r, "cameras", "id", [c.id for c in stage.cameras])
    _no_duplicates(r, "groups", "name", [g.name for g in stage.groups])
    _no_duplicates(r, "lights", "index", [lt.index for lt in stage.lights])
    indices = [lt.index for lt in stage.lights]
    if indices != list(range(len(indices))):
        raise r.fail("lights", "indices must be 0, 1, ..., N-1 in file order (0-based)")
    for i, c in enumerate(stage.cameras):
        where = f"cameras[{i}] ({c.id})"
        if c.fx <= 0 or c.fy <= 0:
            raise r.fail(where + ".intrinsics", f"focal lengths must be positive, got fx={c.fx}, fy={c.fy}")
        if not (0 <= c.cx <= stage.width and 0 <= c.cy <= stage.height):
            raise r.fail(where + ".intrinsics", f"principal point ({c.cx}, {c.cy}) outside the image")
        R = np.asarray(c.R)
        if np.abs(R @ R.T - np.eye(3)).max() > 1e-6 or np.linalg.det(R) < 0:
            raise r.fail(where + ".pose.R", "not a rotation matrix (R R^T != I or det != +1)")
    direction = np.asarray(stage.axis.direction)
    if abs(np.linalg.norm(direction) - 1.0) > 1e-6:
        raise r.fail("turntable_axis.direction", "must be a unit vector")
    floor = -stage.centre_height
    for lt in stage.lights:
        if len(lt.intensity) != 3 or not all(x > 0 for x in lt.intensity):
            raise r.fail(f"lights[{lt.index}].intensity", f"must be 3 positive numbers, got {lt.intensity}")
        if not lt.directional and lt.position[2] < floor - 1e-9:
            raise r.fail(
                f"lights[{lt.index}].position",
                f"z = {lt.position[2]:.4f} m is below the floor (z = {floor:.4f} m)",
            )
    for i, g in enumerate(stage.groups):
        if not 0.0 <= g.yaw_deg < 360.0:
            raise r.fail(f"groups[{i}].yaw_deg", f"must be in [0, 360), got {g.yaw_deg}")


def _no_duplicates(r: _Reader, section: str, key: str, values: list[Any]) -> None:
    seen: set[Any] = set()
    for i, v in enumerate(values):
        if v in seen:
            raise r.fail(f"{section}[{i}].{key}", f"duplicate {key} {v!r}")
        seen.add(v)


def load_stage(path: str | os.PathLike[str]) -> Stage:
    """Read and validate a stage.yaml."""
    path = Path(path)
    return stage_from_dict(read_yaml(path, "stage description"), str(path))
