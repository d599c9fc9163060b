"""Lat-long HDR environment maps: loading, solid-angle-weighted area resampling, orientation in the world
frame, per-pixel directions and solid angles, and median-cut light extraction (Debevec 2008).

Orientation (docs/relighting.md): the top image row is the zenith +z, the bottom row the nadir -z. Longitude 0
(the image centre column) points along +x and longitude increases towards the LEFT of the image, so the left
quarter column looks along +y and the right quarter along -y (the panorama is seen from inside, not mirrored).
`rotate_deg` turns the whole map about +z (right-handed): content at longitude phi moves to phi + rotate_deg.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from lightstage.cameras import rotation_z
from lightstage.errors import LightstageError
from lightstage.tonemap import LUMA

# Rec. 709 / sRGB primaries luminance weights, used for the median-cut energy.
LUMINANCE = np.array(LUMA)  # float64: median cut sums many small energies
DEFAULT_RESOLUTION = (32, 16)  # (width, height) as in the paper / NRTF


@dataclass(frozen=True)
class EnvMap:
    """A lat-long map of linear RGB radiance (H, W, 3) with its rotation about +z in degrees."""

    radiance: np.ndarray
    rotate_deg: float = 0.0

    def __post_init__(self) -> None:
        r = np.asarray(self.radiance)
        if r.ndim != 3 or r.shape[2] != 3 or r.shape[0] < 1 or r.shape[1] < 1:
            raise LightstageError(f"envmap must be (H, W, 3) RGB, got shape {r.shape}")

    @property
    def height(self) -> int:
        return int(self.radiance.shape[0])

    @property
    def width(self) -> int:
        return int(self.radiance.shape[1])

    def solid_angles(self) -> np.ndarray:
        """(H, W) exact solid angle of each pixel (steradians, sums to 4 pi)."""
        return np.broadcast_to(row_solid_angles(self.height, self.width)[:, None], (self.height, self.width))

    def directions(self) -> np.ndarray:
        """(H, W, 3) world-frame unit direction of each pixel centre (towards the light), rotation applied."""
        return pixel_directions(self.height, self.width, self.rotate_deg)

    def energies(self) -> np.ndarray:
        """(H, W, 3) radiance x solid angle per pixel: the irradiance each pixel delivers at normal incidence."""
        return np.asarray(self.radiance, dtype=np.float64) * self.solid_angles()[..., None]


def row_latitudes(height: int) -> np.ndarray:
    """(H,) latitude (radians) of each row's pixel centre: +pi/2 at the top edge, -pi/2 at the bottom edge."""
    return np.pi / 2 - np.pi * (np.arange(height) + 0.5) / height


def column_longitudes(width: int) -> np.ndarray:
    """(W,) longitude (radians) of each column's pixel centre: 0 at the centre, +pi at the left edge."""
    return np.pi - 2 * np.pi * (np.arange(width) + 0.5) / width


def row_solid_angles(height: int, width: int) -> np.ndarray:
    """(H,) exact solid angle of one pixel in each row: (2 pi / W) (sin lat_top - sin lat_bottom)."""
    edges = np.pi / 2 - np.pi * np.arange(height + 1) / height
    return (2 * np.pi / width) * (np.sin(edges[:-1]) - np.sin(edges[1:]))


def direction_from_latlong(lat: np.ndarray, lon: np.ndarray, rotate_deg: float = 0.0) -> np.ndarray:
    """Unit world directions (..., 3) for latitude/longitude (radians) under the documented orientation."""
    lat, lon = np.broadcast_arrays(np.asarray(lat, np.float64), np.asarray(lon, np.float64))
    d = np.stack([np.cos(lat) * np.cos(lon), np.cos(lat) * np.sin(lon), np.sin(lat)], axis=-1)
    return d @ rotation_z(np.deg2rad(rotate_deg)).T if rotate_deg else d


def pixel_directions(height: int, width: int, rotate_deg: float = 0.0) -> np.ndarray:
    """(H, W, 3) unit directions of the pixel centres of an H x W lat-long map."""
    lat, lon = np.meshgrid(row_latitudes(height), column_longitudes(width), indexing="ij")
    return direction_from_latlong(lat, lon, rotate_deg)


def pixel_of_direction(
    direction: np.ndarray, height: int, width: int, rotate_deg: float = 0.0
) -> tuple[int, int]:
    """(row, column) of the pixel of an H x W map that contains a world direction (inverse of the above)."""
    d = np.asarray(direction, np.float64)
    d = rotation_z(-np.deg2rad(rotate_deg)) @ (d / np.linalg.norm(d))
    lat = np.arcsin(np.clip(d[2], -1.0, 1.0))
    lon = np.arctan2(d[1], d[0])
    row = int(np.clip(np.floor((np.pi / 2 - lat) / np.pi * height), 0, height - 1))
    col = int(np.clip(np.floor((np.pi - lon) / (2 * np.pi) * width), 0, width - 1))
    return row, col


def resample(radiance: np.ndarray, width: int, height: int) -> np.ndarray:
    """Area-resample a lat-long radiance map to width x height, weighting source pixels by solid angle.

    cv2.resize(INTER_AREA) of (L * Omega) divided by the resampled Omega: a solid-angle-weighted mean
    radiance per target pixel, so the map's total energy (sum L * Omega) is preserved.
    """
    import cv2

    src = np.asarray(radiance, dtype=np.float32)
    h, w = src.shape[:2]
    if (w, h) == (width, height):
        return src.astype(np.float64)
    omega = np.repeat(row_solid_angles(h, w)[:, None], w, axis=1).astype(np.float32)
    num = cv2.resize(src * omega[..., None], (width, height), interpolation=cv2.INTER_AREA)
    den = cv2.resize(omega, (width, height), interpolation=cv2.INTER_AREA)
    return num.astype(np.float64) / np.maximum(den.astype(np.float64), 1e-30)[..., None]


def load_envmap(
    path: str | os.PathLike[str],
    resolution: tuple[int, int] | None = DEFAULT_RESOLUTION,
    rotate_deg: float = 0.0,
) -> EnvMap:
    """Read a lat-long HDR map (EXR via OpenEXR, .hdr and others via OpenImageIO), resampled to
    `resolution` = (width, height) (None keeps the file's resolution)."""
    from lightstage.frames import read_image

    path = Path(path)
    img = read_image(path)
    if img.shape[2] == 1 or img.shape[2] == 2:  # grey (+ alpha): replicate
        img = np.repeat(img[..., :1], 3, axis=2)
    img = img[..., :3]
    if not np.all(np.isfinite(img)):
        bad = int(np.count_nonzero(~np.isfinite(img)))
        raise LightstageError(f"{path}: envmap has {bad} non-finite (NaN/inf) values")
    if float(img.min()) < 0:
        raise LightstageError(f"{path}: envmap has negative radiance (min {float(img.min()):g})")
    if resolution is not None:
        w, h = resolution
        if w < 1 or h < 1:
            raise LightstageError(f"envmap resolution must be positive, got {w}x{h}")
        img = resample(img, w, h)
    return EnvMap(np.asarray(img, dtype=np.float64), float(rotate_deg))


def parse_resolution(text: str) -> tuple[int, int]:
    """'32x16' -> (32, 16); a LightstageError for anything else."""
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise LightstageError(f"resolution must look like 32x16, got {text!r}") from None
    if w < 1 or h < 1:
        raise LightstageError(f"resolution must be positive, got {text!r}")
    return w, h


@dataclass(frozen=True)
class Region:
    """A rectangle of envmap pixels [row0, row1) x [col0, col1)."""

    row0: int
    row1: int
    col0: int
    col1: int


@dataclass(frozen=True)
class Lights:
    """Directional lights at infinity extracted from an envmap: unit directions (K, 3) and RGB energies
    (K, 3) = sum of radiance x solid angle over each light's pixels (irradiance units)."""

    directions: np.ndarray
    rgb: np.ndarray
    regions: tuple[Region, ...] = ()
    solid_angles: np.ndarray | None = None  # (K,) steradians covered by each light

    def __len__(self) -> int:
        return int(self.directions.shape[0])

    def nonzero(self) -> Lights:
        """Only the lights carrying energy (zero lights contribute exactly nothing)."""
        keep = np.any(self.rgb > 0, axis=1)
        regions = tuple(r for r, k in zip(self.regions, keep, strict=False) if k) if self.regions else ()
        sa = self.solid_angles[keep] if self.solid_angles is not None else None
        return Lights(self.directions[keep], self.rgb[keep], regions, sa)


def all_pixel_lights(env: EnvMap) -> Lights:
    """Every pixel as one light at its centre direction (the exact reference for median cut)."""
    h, w = env.height, env.width
    regions = tuple(Region(r, r + 1, c, c + 1) for r in range(h) for c in range(w))
    return Lights(
        env.directions().reshape(-1, 3),
        env.energies().reshape(-1, 3),
        regions,
        env.solid_angles().reshape(-1).copy(),
    )


def _sat(a: np.ndarray) -> np.ndarray:
    """Summed-area table with a zero first row and column: S[r, c] = sum of a[:r, :c]."""
    s = np.zeros((a.shape[0] + 1, a.shape[1] + 1), dtype=np.float64)
    s[1:, 1:] = np.cumsum(np.cumsum(a, axis=0), axis=1)
    return s


def _box(s: np.ndarray, r0: int, r1: int, c0: int, c1: int) -> float:
    return float(s[r1, c1] - s[r0, c1] - s[r1, c0] + s[r0, c0])


def median_cut_regions(env: EnvMap, num_lights: int) -> list[Region]:
    """Split the map into `num_lights` (a power of two) regions of about equal luminance energy.

    Energies are luminance x pixel solid angle (the cos(latitude) weighting); each region is cut across its
    longer side, the width measured as longitude extent x cos(latitude of the region centre), at the column
    or row boundary closest to half its energy. A single pixel is not split; the most energetic splittable
    regions split in its place, so exactly `num_lights` regions come out.
    """
    if num_lights < 1 or num_lights & (num_lights - 1):
        raise LightstageError(f"the number of median-cut lights must be a power of two, got {num_lights}")
    h, w = env.height, env.width
    if num_lights > h * w:
        raise LightstageError(
            f"{num_lights} lights requested but the envmap has only {w}x{h} = {h * w} pixels"
        )
    energy = (np.asarray(env.radiance, np.float64) @ LUMINANCE) * env.solid_angles()
    sat = _sat(np.maximum(energy, 0.0))
    lat = row_latitudes(h)
    dlon, dlat = 2 * np.pi / w, np.pi / h
    regions = [Region(0, h, 0, w)]
    while len(regions) < num_lights:
        # Normally every region splits (one level of the binary tree); single pixels cannot, and then the
        # most energetic splittable regions split instead so exactly `num_lights` regions come out.
        splittable = [i for i, r in enumerate(regions) if r.row1 - r.row0 > 1 or r.col1 - r.col0 > 1]
        if not splittable:
            break
        total = max(float(sat[-1, -1]), 1e-300)
        # most energetic first; energies rounded so rounding-level ties keep the image order (scale-invariant)
        splittable.sort(key=lambda i: -round(_box(sat, *_bounds(regions[i])) / total, 9))
        chosen = set(splittable[: num_lights - len(regions)])
        regions = [
            part
            for i, r in enumerate(regions)
            for part in (_split(r, sat, lat, dlon, dlat) if i in chosen else [r])
        ]
    return regions


def _bounds(reg: Region) -> tuple[int, int, int, int]:
    return reg.row0, reg.row1, reg.col0, reg.col1


def _split(reg: Region, sat: np.ndarray, lat: np.ndarray, dlon: float, dlat: float) -> list[Region]:
    """Cut one region in two at its energy median across its (cos-latitude weighted) longer side."""
    rows, cols = reg.row1 - reg.row0, reg.col1 - reg.col0
    if rows == 1 and cols == 1:
        return [reg]
    lat_mid = 0.5 * (lat[reg.row0] + lat[reg.row1 - 1])
    width = cols * dlon * np.cos(lat_mid)
    height = rows * dlat
    cut_cols = (width >= height and cols > 1) or rows == 1
    total = _box(sat, reg.row0, reg.row1, reg.col0, reg.col1)
    if cut_cols:
        cuts = np.arange(reg.col0 + 1, reg.col1)
        left = sat[reg.row1, cuts] - sat[reg.row0, cuts] - sat[reg.row1, reg.col0] + sat[reg.row0, reg.col0]
    else:
        cuts = np.arange(reg.row0 + 1, reg.row1)
        left = sat[cuts, reg.col1] - sat[cuts, reg.col0] - sat[reg.row0, reg.col1] + sat[reg.row0, reg.col0]
    mid = 0.5 * (cuts[0] + cuts[-1])
    if total > 0:
        # energy median; near-ties (rounding level) go to the geometric middle so that scaling the map
        # never changes the cuts
        dev = np.abs(left - 0.5 * total)
        near = np.flatnonzero(dev <= dev.min() + 1e-9 * total)
        k = int(cuts[near[np.argmin(np.abs(cuts[near] - mid))]])
    else:  # no energy: split geometrically
        k = int(cuts[len(cuts) // 2])
    if cut_cols:
        return [Region(reg.row0, reg.row1, reg.col0, k), Region(reg.row0, reg.row1, k, reg.col1)]
    return [Region(reg.row0, k, reg.col0, reg.col1), Region(k, reg.row1, reg.col0, reg.col1)]


def lights_from_regions(env: EnvMap, regions: list[Region]) -> Lights:
    """One light per region: direction = luminance-energy centroid of the region's pixel directions
    (renormalised; the solid-angle centroid for a dark region), RGB = sum of radiance x solid angle."""
    dirs = env.directions()
    omega = env.solid_angles()
    energies = env.energies()
    lum = np.maximum(energies @ LUMINANCE, 0.0)
    out_d, out_rgb, out_sa = [], [], []
    for reg in regions:
        sl = (slice(reg.row0, reg.row1), slice(reg.col0, reg.col1))
        weights = lum[sl]
        if not weights.sum() > 0:
            weights = omega[sl]
        c = np.tensordot(weights, dirs[sl], axes=([0, 1], [0, 1]))
        n = np.linalg.norm(c)
        if n < 1e-12:  # symmetric region (e.g. a whole latitude ring of the full map): use its middle pixel
            c = dirs[(reg.row0 + reg.row1) // 2, (reg.col0 + reg.col1) // 2]
            n = 1.0
        out_d.append(c / n)
        out_rgb.append(energies[sl].sum(axis=(0, 1)))
        out_sa.append(omega[sl].sum())
    return Lights(np.asarray(out_d), np.asarray(out_rgb), tuple(regions), np.asarray(out_sa))


def median_cut(env: EnvMap, num_lights: int) -> Lights:
    """Median-cut lights of an envmap (Debevec 2008): see `median_cut_regions` and `lights_from_regions`."""
    return lights_from_regions(env, median_cut_regions(env, num_lights))


def envmap_lights(env: EnvMap, spec: int | str) -> Lights:
    """Lights for a `--lights` value: a power of two (median cut) or 'all' (every pixel)."""
    if spec == "all":
        return all_pixel_lights(env)
    return median_cut(env, int(spec))


def preview_with_lights(
    env: EnvMap, lights: Lights, scale: int = 16, exposure: float | None = None
) -> np.ndarray:
    """uint8 RGB picture of the map (nearest-neighbour upscaled) with region outlines and light positions."""
    import cv2

    from lightstage.tonemap import auto_exposure, tonemap_u8

    exposure = auto_exposure(env.radiance, 99.0) if exposure is None else exposure
    img = tonemap_u8(np.repeat(np.repeat(env.radiance, scale, axis=0), scale, axis=1), exposure)
    img = np.ascontiguousarray(img)
    for reg in lights.regions:
        if reg.row1 - reg.row0 == 1 and reg.col1 - reg.col0 == 1 and len(lights.regions) > 256:
            continue
        cv2.rectangle(
            img,
            (reg.col0 * scale, reg.row0 * scale),
            (reg.col1 * scale - 1, reg.row1 * scale - 1),
            (0, 255, 0),
            1,
        )
    for d in lights.directions:
        r, c = _continuous_pixel(d, env.height, env.width, env.rotate_deg)
        cv2.circle(img, (int(c * scale), int(r * scale)), max(2, scale // 5), (255, 0, 0), -1)
    return img


def _continuous_pixel(
    direction: np.ndarray, height: int, width: int, rotate_deg: float
) -> tuple[float, float]:
    d = rotation_z(-np.deg2rad(rotate_deg)) @ np.asarray(direction, np.float64)
    lat = np.arcsin(np.clip(d[2], -1.0, 1.0))
    lon = np.arctan2(d[1], d[0])
    return (np.pi / 2 - lat) / np.pi * height, (np.pi - lon) / (2 * np.pi) * width


def procedural_sky(width: int = 64, height: int = 32) -> np.ndarray:
    """(H, W, 3) float32 synthetic lat-long sky (the demo's and the viewer's built-in map): a blue gradient
    above the horizon, a dim ground, a small bright sun 45 deg up."""
    lat = (0.5 - (np.arange(height) + 0.5) / height) * np.pi  # +pi/2 at the top row
    lon = ((np.arange(width) + 0.5) / width) * 2 * np.pi - np.pi
    lat_g, lon_g = np.meshgrid(lat, lon, indexing="ij")
    up = np.clip(np.sin(lat_g), 0, None)[..., None]
    img = np.where(lat_g[..., None] > 0, np.array([0.25, 0.45, 0.9]) * (0.4 + 0.6 * up), [0.08, 0.07, 0.06])
    sun = np.exp(
        -(((lat_g - np.deg2rad(45)) ** 2 + (lon_g - np.deg2rad(30)) ** 2) / (2 * np.deg2rad(4) ** 2))
    )
    return (img + 40.0 * sun[..., None] * np.array([1.0, 0.95, 0.85])).astype(np.float32)
