"""Named failure cases of real captures, as options of the simulator (`simulate_capture(..., cases=[...])`,
`lightstage simulate --case NAME`); each changes the scene, the sensor or the stage's lights, and any set of
them combines (docs/simulator.md). Tests use them to reproduce what real photographs did to preprocess."""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import replace

import numpy as np

from lightstage.capture.presets import fibonacci_cap
from lightstage.capture.stage import Stage
from lightstage.errors import LightstageError
from lightstage.simulator.scene import Cylinder, Ellipsoid, Material, SimScene


def _grey_object(scene: SimScene) -> SimScene:
    """An evenly grey matte sphere (Lambertian, no texture, no translucency, no highlight) on a grey stand."""
    return replace(
        scene,
        body=(Ellipsoid("sphere", (0.0, 0.0, 0.0), (0.06, 0.06, 0.06)),),
        core=Ellipsoid("core", (0.0, 0.0, 0.0), (0.001, 0.001, 0.001)),
        stand=Cylinder("stand", (0.0, 0.0), 0.02, -0.45, -0.055),
        material=Material(
            kd=0.95,
            kt=0.0,
            ks=0.0,
            wrap=0.0,
            core_opacity=0.0,
            base_rgb=(0.45, 0.45, 0.45),
            stand_rgb=(0.3, 0.3, 0.3),
            texture=False,
        ),
    )


def _candle(scene: SimScene) -> SimScene:
    """A rotationally symmetric, evenly coloured wax candle on a plain stand, centred on the turntable axis: the
    rig turns around it, so every group sees the same image of it."""
    return replace(
        scene,
        body=(Ellipsoid("candle", (0.0, 0.0, -0.01), (0.045, 0.045, 0.075)),),
        core=Ellipsoid("core", (0.0, 0.0, 0.0), (0.001, 0.001, 0.001)),
        stand=Cylinder("stand", (0.0, 0.0), 0.024, -0.45, -0.08),
        material=replace(scene.material, core_opacity=0.0, texture=False, dark_fraction=0.0),
    )


def _speculars(scene: SimScene) -> SimScene:
    """A glossy object: highlights that clip in the frames of lights near the mirror direction (no light in view)."""
    return replace(scene, material=replace(scene.material, ks=0.18, kd=0.35, shininess=300.0))


def _srgb8(scene: SimScene) -> SimScene:
    """An 8-bit sRGB-like source: gamma-2.2 quantisation to 8 bits after the black level is removed, so the
    darks of a frame are exactly 0."""
    nz = replace(scene.nuisances, quantise_bits=8, quantise_gamma=2.2, black_level=0.0)
    return replace(scene, nuisances=nz)


def _dark_cloth(scene: SimScene) -> SimScene:
    """A dark cloth behind the object: the lit backdrop 11 stops below the cutoff."""
    return replace(scene, nuisances=replace(scene.nuisances, backdrop_stops=11.0))


def _soft_shadows(scene: SimScene) -> SimScene:
    """The object's soft shadows on the cloth (each light casts one)."""
    return replace(scene, nuisances=replace(scene.nuisances, shadow_penumbra=0.04))


def _lit_floor(scene: SimScene) -> SimScene:
    """A lit floor filling the lower 30% of the frames of cameras below the stage centre."""
    return replace(scene, nuisances=replace(scene.nuisances, lit_floor=0.3))


SCENE_CASES: dict[str, Callable[[SimScene], SimScene]] = {
    "grey-object": _grey_object,
    "candle": _candle,
    "speculars": _speculars,
    "srgb8": _srgb8,
    "dark-cloth": _dark_cloth,
    "soft-shadows": _soft_shadows,
    "lit-floor": _lit_floor,
}
STAGE_CASES = ("camera-side-lights",)
CASES = (*SCENE_CASES, *STAGE_CASES)

# camera-side-lights: the lights lie within this angle of the cameras' mean direction (a photometric-stereo rig)
CAMERA_SIDE_CAP_DEG = 60.0


def check_cases(cases: Iterable[str] | None) -> tuple[str, ...]:
    """The cases as a tuple in CASES order; an unknown name is an error naming the known ones."""
    names = tuple(cases or ())
    bad = [c for c in names if c not in CASES]
    if bad:
        raise LightstageError(f"unknown simulator case {bad[0]!r} (known: {', '.join(CASES)})")
    return tuple(c for c in CASES if c in names)


def apply_scene_cases(scene: SimScene, cases: tuple[str, ...]) -> SimScene:
    """The scene with every scene case applied (in CASES order)."""
    for c in cases:
        if c in SCENE_CASES:
            scene = SCENE_CASES[c](scene)
    return scene


def apply_stage_cases(stage: Stage, cases: tuple[str, ...]) -> Stage:
    """camera-side-lights: the stage's lights moved onto a cap of CAMERA_SIDE_CAP_DEG around the cameras' mean
    direction (rig frame), at the light sphere's radius: every light is on the cameras' side of the object."""
    if "camera-side-lights" not in cases:
        return stage
    centres = np.stack([-c.R.T @ c.t for c in stage.cameras])
    axis = centres.mean(axis=0)
    axis /= np.linalg.norm(axis)
    cap = fibonacci_cap(len(stage.lights), CAMERA_SIDE_CAP_DEG)  # around +z
    z = np.array([0.0, 0.0, 1.0])
    v = np.cross(z, axis)
    s, c = float(np.linalg.norm(v)), float(z @ axis)
    if s < 1e-9:
        rot = np.eye(3) * (1.0 if c > 0 else -1.0)
    else:
        k = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]]) / s
        rot = np.eye(3) + s * k + (1 - c) * (k @ k)  # Rodrigues: +z onto `axis`
    positions = (cap @ rot.T) * stage.sphere_radius
    lights = tuple(replace(lt, position=p) for lt, p in zip(stage.lights, positions, strict=True))
    return replace(stage, lights=lights)
