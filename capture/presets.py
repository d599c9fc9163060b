"""Built-in stage presets. `paper` is the reference light stage of the paper; `make_stage` builds scaled
versions of the same geometry (fewer cameras/lights, smaller sensors) for the simulator's presets."""

from __future__ import annotations

import numpy as np

from lightstage.cameras import look_at
from lightstage.capture.stage import CameraSpec, GroupSpec, LightSpec, Stage, validate_stage
from lightstage.errors import LightstageError

PAPER_RESOLUTION = (8192, 5464)
PAPER_SATURATION = 4.4019
PAPER_SPHERE_RADIUS = 1.5
PAPER_CENTRE_HEIGHT = 1.1
# Lights span polar angles [0, 135 deg] from the zenith (paper §4: no light has negative altitude).
MAX_LIGHT_POLAR_DEG = 135.0
# Cameras look at the object from a sphere of this radius; focal length as a multiple of image width.
FOCAL_PER_WIDTH = 2.7
CAMERA_ELEVATIONS_DEG = (-10.0, 10.0, 30.0, 50.0)


def fibonacci_cap(n: int, max_polar_deg: float) -> np.ndarray:
    """(n, 3) unit vectors evenly spread over the spherical cap of polar angle <= max_polar_deg (+z zenith)."""
    z_min = np.cos(np.deg2rad(max_polar_deg))
    k = np.arange(n) + 0.5
    z = 1.0 - k / n * (1.0 - z_min)
    phi = k * np.pi * (3.0 - np.sqrt(5.0))
    r = np.sqrt(1.0 - z**2)
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=-1)


def camera_directions(n: int) -> np.ndarray:
    """(n, 3) unit directions from the centre to the cameras: rings of elevation, staggered azimuths."""
    rings = len(CAMERA_ELEVATIONS_DEG)
    per_ring = [n // rings + (1 if i < n % rings else 0) for i in range(rings)]
    dirs = []
    for ring, (elev, count) in enumerate(zip(CAMERA_ELEVATIONS_DEG, per_ring, strict=True)):
        for k in range(count):
            az = np.deg2rad(20.0 * k + 10.0 * (ring % 2))
            el = np.deg2rad(elev)
            dirs.append([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
    return np.asarray(dirs)


def make_stage(
    name: str,
    num_cameras: int = 20,
    num_lights: int = 331,
    width: int = PAPER_RESOLUTION[0],
    height: int = PAPER_RESOLUTION[1],
    num_groups: int = 9,
    saturation: float = PAPER_SATURATION,
    sphere_radius: float = PAPER_SPHERE_RADIUS,
    centre_height: float = PAPER_CENTRE_HEIGHT,
    camera_distance: float | None = None,
) -> Stage:
    """A stage with the reference geometry: cameras on rings looking at the centre, lights on the
    bottom-truncated sphere, groups at 360/num_groups degree steps."""
    if num_cameras < 1 or num_lights < 1 or num_groups < 1:
        raise LightstageError(f"preset {name!r}: counts must be positive")
    dist = sphere_radius if camera_distance is None else camera_distance
    f = FOCAL_PER_WIDTH * width
    cameras = []
    for i, d in enumerate(camera_directions(num_cameras)):
        R, t = look_at(d * dist, np.zeros(3))
        cameras.append(CameraSpec(f"cam{i:02d}", f, f, width / 2.0, height / 2.0, R, t))
    positions = fibonacci_cap(num_lights, MAX_LIGHT_POLAR_DEG) * sphere_radius
    lights = [LightSpec(i, p) for i, p in enumerate(positions)]
    step = 360.0 / num_groups
    groups = [GroupSpec(f"{round(g * step):03d}", g * step) for g in range(num_groups)]
    stage = Stage(
        name=name,
        cameras=tuple(cameras),
        lights=tuple(lights),
        groups=tuple(groups),
        width=width,
        height=height,
        saturation=saturation,
        sphere_radius=sphere_radius,
        centre_height=centre_height,
    )
    validate_stage(stage, f"preset {name}")
    return stage


def paper_stage() -> Stage:
    """The reference stage: 20 cameras, 331 lights, 9 groups, 8192x5464, cutoff 4.4019."""
    return make_stage("paper")


STAGE_PRESETS = {"paper": paper_stage}


def stage_preset(name: str) -> Stage:
    """A built-in stage by name."""
    try:
        return STAGE_PRESETS[name]()
    except KeyError:
        raise LightstageError(f"unknown stage preset {name!r} (known: {', '.join(STAGE_PRESETS)})") from None
