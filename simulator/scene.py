"""The simulator's analytic scene: a translucent object (union of ellipsoids) with an opaque textured core,
on a dark cylindrical stand, and its solid textures; simulator/shading.py casts rays into it and shades them.

Shading (per point light of intensity I at distance r, irradiance E = I / r^2, all terms linear in I):
  object  = E * vis * [ (kd * wrap(n.l) + kt * T_rgb * max(n_e.l, 0) / pi) * albedo_rgb + ks * blinn(n, l, v) ]
  stand   = E * exp(-sigma_shadow * thickness) * [ albedo * max(n.l, 0) / pi + ks_stand * blinn ]
with wrap(x) = max(x + w, 0) / (pi (1 + w)^2) (energy-normalised wrapped diffuse), T_rgb = exp(-sigma_tr * d)
the diffusion attenuation over the distance d travelled inside the object along the light ray, n_e the normal
where the light enters, and vis the stand's (opaque) occlusion. kd + kt + ks <= 1 keeps it energy-conserving.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, replace
from typing import Any

import numpy as np
from scipy import ndimage

from lightstage.config import load
from lightstage.errors import LightstageError

KIND_NONE, KIND_OBJECT, KIND_STAND = 0, 1, 2


@dataclass(frozen=True)
class Ellipsoid:
    """Axis-aligned ellipsoid: centre and semi-axes in world metres."""

    name: str
    centre: tuple[float, float, float]
    radii: tuple[float, float, float]


@dataclass(frozen=True)
class Cylinder:
    """Vertical capped cylinder (the stand): axis through (x, y), radius, z range, world metres."""

    name: str
    centre_xy: tuple[float, float]
    radius: float
    z_min: float
    z_max: float


@dataclass(frozen=True)
class Material:
    """Parameters of the translucent object's approximate subsurface-scattering model (see module doc)."""

    kd: float = 0.42  # wrapped-diffuse weight
    kt: float = 0.4  # diffusion weight (re-emerging on the lit side or transmitted through)
    ks: float = 0.05  # specular weight
    shininess: float = 90.0
    wrap: float = 0.4
    sigma_tr: tuple[float, float, float] = (
        14.0,
        24.0,
        42.0,
    )  # 1/m, diffusion attenuation (red travels furthest)
    sigma_shadow: float = 90.0  # 1/m, extinction of the direct light through the object (stand shadows)
    sigma_view: float = 30.0  # 1/m, how quickly the inner core fades with depth below the surface
    core_opacity: float = 0.85
    base_rgb: tuple[float, float, float] = (0.92, 0.78, 0.58)  # candle/soap wax
    core_rgb: tuple[float, float, float] = (0.35, 0.12, 0.06)
    stand_rgb: tuple[float, float, float] = (0.07, 0.07, 0.08)
    stand_ks: float = 0.03
    # dark-albedo regions (paint, dirt, dark inclusions at the surface): about this fraction of the surface,
    # in patches of 1-4 cm, has its albedo multiplied by `dark_albedo` (in the clean ground truth too)
    dark_fraction: float = 0.0
    dark_albedo: float = 0.1
    # False: every surface point has exactly `base_rgb` (an evenly coloured object; no veins, flecks, mottling)
    texture: bool = True


@dataclass(frozen=True)
class Nuisances:
    """Light-stage nuisances added to the raw frames only (never to the clean ground truth)."""

    background: float = 4.0e-4  # dark background level
    read_noise: float = 1.5e-4  # std of the additive read noise
    shot_gain: float = 4.0e-5  # variance per unit signal (Poisson-like)
    adc_step: float = 1.0 / 4096  # quantisation step of the (14-bit-like) converter
    bulb_radius: float = 0.02  # m
    bulb_radiance: float = 500.0  # far above the cutoff: bulbs in view clip
    flare_max_angle_deg: float = 14.0  # flare when the light is within this angle of the optical axis ...
    flare_gain: float = 0.25  # ... and behind the object; peak added radiance per unit camera irradiance
    flare_sigma: float = 0.10  # glow width as a fraction of the image width
    # ---- a real stage's background and sensor (all off by default: the clean, dark render of old; the
    # `stage` profile of `realistic_nuisances` turns them on)
    # textured cloth backdrop and stage structure, fixed to the camera (they turn with the rig), lit by the
    # same lights (LEDs aimed at the centre, so a light lights the backdrop only when it faces it): its mean
    # radiance where a light faces it squarely, as stops below the cutoff (0: no backdrop)
    backdrop_stops: float = 0.0
    backdrop_texture: float = 0.45  # relative spread of the cloth's albedo (weave and folds)
    structure_gain: float = 2.5  # stage structure (bars) is this much brighter than the cloth
    black_level: float = 0.0  # sensor offset (stage units) added before and subtracted after quantisation
    quantise_bits: int = 0  # 8 or 12: quantise value/cutoff to this many bits (0: the adc_step converter)
    quantise_gamma: float = 1.0  # transfer curve of the quantiser (1: linear; 2.2: an 8-bit sRGB-like source)
    # a lit floor (or table top) in the lower part of a low camera's frame (camera below the stage centre):
    # this fraction of the frame height, `floor_gain` times the cloth's brightness; fixed to the camera like the
    # backdrop, so it looks the same in every group (0: none)
    lit_floor: float = 0.0
    floor_gain: float = 4.0
    # soft shadows of the object on the backdrop: the object's silhouette seen from each light, projected onto
    # the cloth and blurred by this penumbra width (metres on the cloth; 0: no shadows)
    shadow_penumbra: float = 0.0


@dataclass(frozen=True)
class SimScene:
    """Everything needed to render the scene (saved as ground_truth/scene.json)."""

    body: tuple[Ellipsoid, ...]
    core: Ellipsoid
    stand: Cylinder
    material: Material = field(default_factory=Material)
    nuisances: Nuisances = field(default_factory=Nuisances)
    light_intensity: float = 6.0
    texture_seed: int = 0
    # per-light RGB emission relative to light_intensity (real LEDs differ by tens of percent and in colour):
    # log-normal spread of the brightness and of each channel; recorded in stage.yaml as lights[i].intensity
    led_spread: float = 0.0
    led_colour_spread: float = 0.0

    def bounding_box(self) -> tuple[list[float], list[float]]:
        """World bounds (min, max) of the translucent object (not the stand)."""
        lo = np.min([np.subtract(e.centre, e.radii) for e in self.body], axis=0)
        hi = np.max([np.add(e.centre, e.radii) for e in self.body], axis=0)
        return lo.tolist(), hi.tolist()

    def to_dict(self) -> dict[str, Any]:
        lo, hi = self.bounding_box()
        d = asdict(self)
        d["object_bbox"] = {"min": lo, "max": hi}
        d["description"] = (
            "translucent wax object (union of the `body` ellipsoids) with an opaque textured inner `core`, "
            "on an opaque dark cylindrical `stand`; world metres"
        )
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any], source: str = "scene description") -> SimScene:
        """Read `to_dict`'s output with the strict loader (its derived `object_bbox` and `description`, and the
        provenance scene.json adds (`seed`, `preset`, `units`), are left out); a misspelt key is one ConfigError."""
        return load(cls, d, source, ignore=("object_bbox", "description", "seed", "preset", "units"))


REALISM = ("stage", "clean")


def realistic_nuisances() -> Nuisances:
    """What a real stage adds (docs/simulator.md): a cloth backdrop and structure lit 8-12 stops below the
    cutoff, a black level with read and shot noise, and a 12-bit converter that quantises the darks."""
    return Nuisances(
        read_noise=1.6e-3,  # ~1.5 DN of the 12-bit converter
        shot_gain=2.2e-4,  # ~20,000 electrons at the cutoff
        backdrop_stops=9.0,
        black_level=0.07,  # ~64 DN
        quantise_bits=12,
    )


def led_intensities(num_lights: int, seed: int, spread: float, colour_spread: float) -> np.ndarray:
    """(num_lights, 3) seeded relative RGB intensities of the stage's LEDs (all 1 without spread)."""
    rng = np.random.default_rng([seed, 11])
    gain = np.exp(spread * rng.standard_normal((num_lights, 1)))
    colour = np.exp(colour_spread * rng.standard_normal((num_lights, 3)))
    return np.round(gain * colour, 4)


def default_scene(texture_seed: int = 0, realism: str = "clean") -> SimScene:
    """The candle/soap-like object: a wax body with a head and a thin fin, a dark core, a dark stand.
    `realism`: "clean" (dark, noise-poor background, equal lights) or "stage" (a real stage's lit backdrop,
    sensor and LEDs, and dark-albedo patches on the object; see `realistic_nuisances`)."""
    if realism not in REALISM:
        raise LightstageError(f"unknown simulator realism {realism!r} (known: {', '.join(REALISM)})")
    if realism == "stage":
        return replace(
            default_scene(texture_seed),
            material=Material(dark_fraction=0.12),
            nuisances=realistic_nuisances(),
            led_spread=0.15,
            led_colour_spread=0.05,
        )
    return SimScene(
        body=(
            Ellipsoid("body", (0.0, 0.0, -0.015), (0.07, 0.05, 0.085)),
            Ellipsoid("head", (0.012, 0.004, 0.072), (0.043, 0.04, 0.042)),
            Ellipsoid("fin", (-0.004, 0.0, 0.0), (0.108, 0.012, 0.05)),
        ),
        core=Ellipsoid("core", (0.0, 0.0, -0.01), (0.036, 0.026, 0.047)),
        stand=Cylinder("stand", (0.0, 0.0), 0.024, -0.45, -0.085),
        texture_seed=texture_seed,
    )


# ---- solid textures ---------------------------------------------------------------------------------
class SolidTexture:
    """Seeded, non-repeating 3D value-noise textures evaluated at world positions (fixed to the object)."""

    GRID = 64

    def __init__(self, seed: int):
        rng = np.random.default_rng([seed, 7])
        self.grids = [rng.random((self.GRID,) * 3, dtype=np.float32) for _ in range(4)]
        # per (field, octave) a random rotation and offset, so octaves never align or repeat together
        self.frames = [
            [(_random_rotation(rng), rng.random(3) * self.GRID) for _ in range(8)] for _ in range(4)
        ]

    def fbm(
        self, fieldno: int, p: np.ndarray, cell_sizes: tuple[float, ...], gain: float = 0.6
    ) -> np.ndarray:
        """Fractal value noise in [0, 1] at (N, 3) world points; cell sizes in metres, coarse first."""
        total = np.zeros(len(p), np.float32)
        weight, norm = 1.0, 0.0
        for k, cell in enumerate(cell_sizes):
            rot, off = self.frames[fieldno][k]
            # explicit products: BLAS matmul on (N, 3) arrays is slow (and thread-hungry) here
            coords = np.stack(
                [
                    (p[:, 0] * rot[i, 0] + p[:, 1] * rot[i, 1] + p[:, 2] * rot[i, 2]) / cell + off[i]
                    for i in range(3)
                ]
            )
            v = ndimage.map_coordinates(self.grids[fieldno], coords, order=1, mode="grid-wrap")
            total += weight * v
            norm += weight
            weight *= gain
        return total / norm


def _random_rotation(rng: np.random.Generator) -> np.ndarray:
    q, r = np.linalg.qr(rng.standard_normal((3, 3)))
    q = q * np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 0] = -q[:, 0]
    return q


def _smoothstep(a: float, b: float, x: np.ndarray) -> np.ndarray:
    t = np.clip((x - a) / (b - a), 0.0, 1.0)
    return t * t * (3 - 2 * t)


def dark_patches(tex: SolidTexture, p: np.ndarray, fraction: float) -> np.ndarray:
    """(N,) weight in [0, 1] of the dark-albedo regions: blobs of 1-4 cm covering about `fraction` of the
    surface (a coarse octave of the blot field, in a region of its grid the flecks do not use)."""
    if fraction <= 0:
        return np.zeros(len(p), np.float32)
    v = tex.fbm(2, p * 0.37 + 3.1, (0.03, 0.015))
    # fbm of two octaves is roughly normal around 0.5 with sd ~0.09: the upper `fraction` tail
    from scipy.special import ndtri

    t = 0.5 + 0.09 * float(ndtri(1.0 - min(fraction, 0.99)))
    return _smoothstep(t - 0.01, t + 0.01, v)


def object_albedo(tex: SolidTexture, p: np.ndarray, base: np.ndarray) -> np.ndarray:
    """(N, 3) surface albedo of the wax: marbled veins, fine mottling and dark flecks (rich for SIFT)."""
    marble = tex.fbm(0, p, (0.05, 0.025, 0.012, 0.006))
    veins = 1.0 - _smoothstep(0.0, 0.05, np.abs(marble - 0.5))
    fine = tex.fbm(1, p, (0.008, 0.004, 0.002))
    blots = tex.fbm(2, p, (0.014, 0.007, 0.0035))
    flecks = _smoothstep(0.56, 0.62, blots)  # dark blots, 3-15 mm, sharp-edged
    pale = _smoothstep(0.40, 0.34, blots)  # and pale ones
    lum = 0.55 + 0.9 * (fine - 0.5)
    lum = lum * (1.0 - 0.6 * veins) * (1.0 - 0.8 * flecks) * (1.0 + 0.6 * pale)
    tint = tex.fbm(3, p, (0.06, 0.03))[:, None]
    colour = base[None, :] * (0.8 + 0.4 * tint * np.array([1.0, 0.85, 0.6], np.float32))
    return np.clip(colour * lum[:, None], 0.0, 1.0).astype(np.float32)


def core_albedo(tex: SolidTexture, p: np.ndarray, base: np.ndarray) -> np.ndarray:
    """(N, 3) albedo of the opaque inner core: banded, mottled."""
    bands = 0.5 + 0.5 * np.sin(p[:, 2] * 260.0 + 6.0 * tex.fbm(1, p, (0.02, 0.01)))
    mott = tex.fbm(2, p * 1.7, (0.006, 0.003))
    lum = 0.4 + 0.6 * bands * mott * 1.6
    return np.clip(base[None, :] * lum[:, None], 0.0, 1.0).astype(np.float32)


def stand_albedo(tex: SolidTexture, p: np.ndarray, base: np.ndarray) -> np.ndarray:
    """(N, 3) albedo of the dark stand: grainy."""
    grain = tex.fbm(3, p, (0.01, 0.004, 0.002))
    return np.clip(base[None, :] * (0.5 + grain[:, None]), 0.0, 1.0).astype(np.float32)
