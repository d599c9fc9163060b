"""Per-view rendering of simulated raw frames: clean scene radiance plus the light-stage nuisances
(dark background, bulbs in view, lens flare, sensor noise, clipping), written as half EXR.

One `ViewJob` renders every light of one view; it is self-contained (picklable) so views run in a process
pool, and its noise is seeded per frame, so the bytes do not depend on scheduling.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from lightstage.cameras import PinholeCamera, pixel_rays
from lightstage.frames import write_exr, write_exr_planes, write_image
from lightstage.ids import ViewId
from lightstage.records.ground_truth import CLEAN_TEMPLATE, GroundTruth
from lightstage.records.processed import to_half
from lightstage.simulator.scene import KIND_NONE, Nuisances, SimScene
from lightstage.simulator.shading import ViewHits, cast_view, first_hit, scatter_rows, shade

# An LED's beam (aimed at the stage centre) lights nothing beyond this angle off its axis.
BEAM_HALF_ANGLE_DEG = 50.0
# Frames with at most this many values share one pool of normals per view (2x the frame).
POOL_MAX_VALUES = 16_000_000
# Values per band of the noise step (add_noise_and_clip): its float32 buffer, the image, the normals and the
# clip mask of a band, ~1.7 MB, fit a core's L2 cache.
NOISE_BAND_VALUES = 1 << 17


@dataclass(frozen=True)
class ViewJob:
    """All inputs needed to render and write one view's frames."""

    root: Path
    group: str
    camera: str
    group_index: int  # indices in the full stage (seed streams do not depend on selections)
    camera_index: int
    camera_model: PinholeCamera  # true camera
    light_positions: np.ndarray  # (L, 3) true world positions
    light_ids: tuple[int, ...]  # 0-based indices written in file names
    light_seed_ids: tuple[int, ...]  # indices for noise seeds
    clean_lights: tuple[int, ...]  # light ids whose clean render is written
    scene: SimScene
    saturation: float
    seed: int
    path_template: str
    # raw frames: PIZ (noisy 12-bit half frames: 0.026 CPU-s and 0.48 MB per 768x512 frame against ZIP's 0.043 s
    # and 1.1 MB); the float32 clean renders keep ZIP (PIZ is 3x slower and larger on them)
    compression: str = "piz"
    attributes: dict = field(default_factory=dict)
    # (L, 3) relative RGB emission of each light (stage.yaml's lights[i].intensity); None: all 1
    light_intensities: np.ndarray | None = None


@dataclass(frozen=True)
class ViewRecord:
    """What a view job reports back (small)."""

    group: str
    camera: str
    foreground_pixels: int
    bulbs: dict[int, int]  # light id -> number of saturated bulb pixels in view
    flares: dict[int, float]  # light id -> flare peak added radiance
    seconds: float


def saturation_value(cutoff: float) -> np.float16:
    """The smallest half-float >= cutoff (what a clipped pixel stores so it still reads as saturated)."""
    h = np.float16(cutoff)
    if float(h) < cutoff:
        h = np.nextafter(h, np.float16(np.inf))
    return h


def background_image(cam: PinholeCamera, level: float) -> np.ndarray:
    """(H, W, 3) dim, slightly vignetted, slightly bluish background (a dark light-stage interior)."""
    y, x = np.mgrid[0 : cam.height, 0 : cam.width].astype(np.float32)
    rr = ((x + 0.5 - cam.width / 2) ** 2 + (y + 0.5 - cam.height / 2) ** 2) / (cam.width / 2) ** 2
    lum = level * (1.0 - 0.35 * np.clip(rr, 0, 1.5))
    return lum[..., None] * np.array([0.9, 0.95, 1.1], np.float32)


def _value_noise(rng: np.random.Generator, shape: tuple[int, int], cells: tuple[int, ...]) -> np.ndarray:
    """(h, w) smooth seeded noise in ~[-1, 1]: octaves of bicubically upsampled random grids (`cells` per
    image height, coarse first, each half the weight of the one before)."""
    import cv2

    h, w = shape
    out = np.zeros(shape, np.float32)
    weight, norm = 1.0, 0.0
    for c in cells:
        gh, gw = max(2, c), max(2, int(round(c * w / h)))
        grid = rng.standard_normal((gh, gw)).astype(np.float32)
        out += weight * cv2.resize(grid, (w, h), interpolation=cv2.INTER_CUBIC)
        norm += weight
        weight *= 0.5
    return out / (norm * 0.8)


@dataclass
class Backdrop:
    """A view's lit background: albedo image and the world points it lies at (fixed to the camera)."""

    albedo: np.ndarray  # (h, w, 3) at `factor` x below the frame
    points: np.ndarray  # (h * w, 3) world points of the backdrop surface
    normal: np.ndarray  # (3,) world normal of the backdrop (towards the camera)
    factor: int
    level: float  # radiance of albedo 1 lit squarely by one light at the reference distance
    occluders: tuple = ()  # the object's ellipsoids, when it casts soft shadows on the backdrop
    penumbra_px: float = 0.0  # their blur (pixels of the albedo grid)


def make_backdrop(
    scene: SimScene, cam: PinholeCamera, camera_index: int, seed: int, cutoff: float
) -> Backdrop:
    """The cloth backdrop and the stage structure seen by one camera: a plane just inside the light sphere
    behind the object, facing the camera; its albedo (weave, folds, a few bars of brighter structure) is
    seeded per camera, so it is the same in every group (it turns with the rig)."""
    nz = scene.nuisances
    rng = np.random.default_rng([seed, 21, camera_index])
    factor = 4
    h, w = max(2, cam.height // factor), max(2, cam.width // factor)
    folds = _value_noise(rng, (h, w), (3, 6))
    weave = _value_noise(rng, (h, w), (40, 80))
    cloth = np.exp(nz.backdrop_texture * (0.8 * folds + 0.4 * weave))
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    structure = np.zeros((h, w), np.float32)
    for _ in range(int(rng.integers(2, 5))):  # struts crossing the frame at random angles
        ang = rng.uniform(0, np.pi)
        off = rng.uniform(-0.45, 0.45) * np.hypot(h, w)
        width = rng.uniform(0.008, 0.03) * np.hypot(h, w)
        dist = (xx - w / 2) * np.cos(ang) + (yy - h / 2) * np.sin(ang) - off
        structure = np.maximum(structure, np.clip(1.0 - np.abs(dist) / width, 0, 1) ** 0.5)
    lum = cloth * (1.0 + (nz.structure_gain - 1.0) * structure)
    if nz.lit_floor > 0 and cam.center[2] < 0:  # a low camera sees the lit floor in its lower rows
        horizon = (1.0 - nz.lit_floor) * h
        floor = np.clip((yy[:, :1] - horizon) / max(0.02 * h, 1.0) + 0.5, 0, 1)
        lum = lum * (1.0 + (nz.floor_gain - 1.0) * floor)
    tint = np.array([0.85, 0.9, 1.15], np.float32) * (1.0 + 0.05 * rng.standard_normal(3)).astype(np.float32)
    albedo = lum[..., None] * tint
    # plane through the far side: the camera's axis meets it 1.35 m behind the centre
    centre = cam.center
    fwd = np.asarray(cam.R[2], np.float64)
    depth = float(np.linalg.norm(centre)) + 1.35
    u = (np.arange(w) + 0.5) * factor
    v = (np.arange(h) + 0.5) * factor
    uu, vv = np.meshgrid(u, v)
    uv = np.stack([uu.ravel(), vv.ravel()], axis=-1)
    o, d = pixel_rays(uv, cam.K, cam.R, cam.t)
    t = depth / np.maximum(d @ fwd, 1e-3)
    points = o + t[:, None] * d
    level = cutoff * 2.0 ** (-nz.backdrop_stops)
    penumbra = 0.0
    if nz.shadow_penumbra > 0:
        penumbra = float(cam.K[0, 0]) / factor * nz.shadow_penumbra / depth
    occluders = scene.body if penumbra > 0 else ()
    return Backdrop(albedo.astype(np.float32), points, -fwd, factor, level, occluders, penumbra)


# what a cast shadow on the backdrop leaves of the light (the rest of the stage fills it in a little)
SHADOW_FLOOR = 0.15


def backdrop_shadow(bd: Backdrop, p: np.ndarray) -> np.ndarray:
    """(h * w,) float32 light reaching each backdrop point from the light at `p` past the object's ellipsoids:
    1 unshadowed, SHADOW_FLOOR in the umbra, blurred by the penumbra (a light is not a point)."""
    import cv2

    from lightstage.simulator.shading import ellipsoid_interval

    to_light = p[None, :] - bd.points
    dist = np.linalg.norm(to_light, axis=-1)
    d = to_light / dist[:, None]
    o = (bd.points[:, 0], bd.points[:, 1], bd.points[:, 2])
    dd = (d[:, 0], d[:, 1], d[:, 2])
    hit = np.zeros(len(dist), bool)
    for e in bd.occluders:
        t0, t1, h = ellipsoid_interval(e, o, dd)
        hit |= h & (t1 > 0) & (t0 < dist)
    h, w = bd.albedo.shape[:2]
    shadow = np.where(hit, SHADOW_FLOOR, 1.0).astype(np.float32).reshape(h, w)
    shadow = cv2.GaussianBlur(shadow, (0, 0), max(bd.penumbra_px, 0.5))
    return shadow.ravel()


def backdrop_frame(
    bd: Backdrop, p: np.ndarray, gain: np.ndarray, shape: tuple[int, int], out: np.ndarray | None = None
) -> np.ndarray:
    """(H, W, 3) backdrop radiance under the light at `p`: an LED aimed at the centre (its beam falls to 0 at
    BEAM_HALF_ANGLE_DEG off its axis, so lights on the far side do not light the backdrop), inverse square from
    the backdrop's typical distance, cosine at the cloth; uneven across the frame by construction. `gain`: the
    light's relative RGB emission. `out`: an (H, W, 3) float32 buffer to upsample into (a view reuses one)."""
    import cv2

    to_pt = bd.points - p[None, :]
    dist = np.linalg.norm(to_pt, axis=-1)
    dirn = to_pt / dist[:, None]
    axis = -p / max(float(np.linalg.norm(p)), 1e-9)
    cos_beam = np.cos(np.deg2rad(BEAM_HALF_ANGLE_DEG))
    emit = np.clip((dirn @ axis - cos_beam) / (1.0 - cos_beam), 0, None) ** 1.5
    incidence = np.clip(-(dirn @ bd.normal), 0, None)
    ref = 2.4  # m: a light on the camera's side to the backdrop
    e = (emit * incidence * (ref / np.maximum(dist, 0.3)) ** 2).astype(np.float32)
    if bd.occluders:
        e *= backdrop_shadow(bd, p)
    h, w = bd.albedo.shape[:2]
    small = bd.albedo * (bd.level * e.reshape(h, w))[..., None] * gain.astype(np.float32)
    return cv2.resize(small, (shape[1], shape[0]), dst=out, interpolation=cv2.INTER_LINEAR)


def bulb_disc(
    cam: PinholeCamera, p: np.ndarray, bulb_radius: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None:
    """(rows, cols, ray origins, ray directions) of the pixels inside the image of a bulb of `bulb_radius` at
    world `p` (at least 1.5 px across), before any occlusion; None when it is behind the camera or off-frame."""
    pc = cam.R @ p + cam.t
    if pc[2] <= 0:
        return None
    u = cam.K[0, 0] * pc[0] / pc[2] + cam.K[0, 2]
    v = cam.K[1, 1] * pc[1] / pc[2] + cam.K[1, 2]
    rad = max(1.5, cam.K[0, 0] * bulb_radius / pc[2])
    c0, c1 = max(int(np.floor(u - rad)), 0), min(int(np.ceil(u + rad)), cam.width)
    r0, r1 = max(int(np.floor(v - rad)), 0), min(int(np.ceil(v + rad)), cam.height)
    if c0 >= c1 or r0 >= r1:
        return None
    rows, cols = np.mgrid[r0:r1, c0:c1]
    inside = (cols + 0.5 - u) ** 2 + (rows + 0.5 - v) ** 2 <= rad**2
    rows, cols = rows[inside], cols[inside]
    if rows.size == 0:
        return None
    o, d = pixel_rays(np.stack([cols + 0.5, rows + 0.5], axis=-1).astype(np.float64), cam.K, cam.R, cam.t)
    return rows, cols, o, d


def bulb_pixels(scene: SimScene, cam: PinholeCamera, p: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """(rows, cols) of pixels showing the unoccluded bulb of a light at world `p`, or None if it is not in view."""
    disc = bulb_disc(cam, p, scene.nuisances.bulb_radius)
    if disc is None:
        return None
    rows, cols, o, d = disc
    t, kind, _ = first_hit(scene, (o[:, 0], o[:, 1], o[:, 2]), (d[:, 0], d[:, 1], d[:, 2]))
    dist = np.linalg.norm(p - cam.center)
    free = (kind == KIND_NONE) | (t > dist)
    if not free.any():
        return None
    return rows[free], cols[free]


def add_flare(
    img: np.ndarray, scene: SimScene, cam: PinholeCamera, p: np.ndarray, intensity: float | np.ndarray
) -> float:
    """Add lens flare (glow + horizontal streak + ghost) in place for a light behind the object near the view
    direction; returns its strength (0: none; for the mean of an RGB intensity). Separable profiles keep it
    cheap; linear in the intensity, per channel (a tinted LED's flare has its tint, so dividing the LED's
    intensity out of the frame leaves the flare of a white LED)."""
    nz = scene.nuisances
    rgb = np.broadcast_to(np.asarray(intensity, np.float64), (3,))
    intensity = float(rgb.mean())
    to_light = p - cam.center
    dist = float(np.linalg.norm(to_light))
    cos_axis = float(cam.R[2] @ to_light) / dist
    angle = np.degrees(np.arccos(np.clip(cos_axis, -1, 1)))
    behind = dist > float(np.linalg.norm(cam.center))  # farther than the object (at the origin)
    if angle >= nz.flare_max_angle_deg or not behind:
        return 0.0
    strength = nz.flare_gain * intensity / dist**2 * (1.0 - angle / nz.flare_max_angle_deg) ** 2
    pc = cam.R @ p + cam.t
    u = cam.K[0, 0] * pc[0] / pc[2] + cam.K[0, 2]
    v = cam.K[1, 1] * pc[1] / pc[2] + cam.K[1, 2]
    x = np.arange(cam.width, dtype=np.float64) + 0.5
    y = np.arange(cam.height, dtype=np.float64) + 0.5
    s = nz.flare_sigma * cam.width
    sg = 0.03 * cam.width
    gu, gv = cam.width - u, cam.height - v  # ghost mirrored through the image centre
    components = (
        # (row profile, column profile, weight, colour)
        (
            np.exp(-((y - v) ** 2) / (2 * s * s)),
            np.exp(-((x - u) ** 2) / (2 * s * s)),
            1.0,
            (1.0, 0.95, 0.85),
        ),
        (
            np.exp(-(((y - v) / (0.006 * cam.width)) ** 2)),
            np.exp(-np.abs(x - u) / (0.35 * cam.width)),
            0.6,
            (0.8, 0.9, 1.0),
        ),
        (
            np.exp(-((y - gv) ** 2) / (2 * sg * sg)),
            np.exp(-((x - gu) ** 2) / (2 * sg * sg)),
            0.35,
            (0.5, 0.8, 1.0),
        ),
    )
    for rows, cols, weight, colour in components:
        rows = rows.astype(np.float32)
        if rows.max() < 1e-7:
            continue
        for c in range(3):
            tint = colour[c] * (rgb[c] / intensity if intensity > 0 else 1.0)
            img[..., c] += np.outer(rows, (strength * weight * tint * cols).astype(np.float32))
    return float(strength)


def add_noise_and_clip(img: np.ndarray, scene: SimScene, cutoff: float, normal: np.ndarray) -> np.ndarray:
    """Poisson-like shot noise + read noise (Gaussian approximation, `normal`: standard normals, one per
    value) on top of the black level, the converter's quantisation (`quantise_bits` of value/cutoff through
    `quantise_gamma`, else steps of `adc_step`), black level subtracted, then clip to [0, cutoff] as float16;
    pixels that reached the cutoff store the smallest half >= cutoff (they read as saturated).

    Runs in row bands of about NOISE_BAND_VALUES values, so its ~17 passes stay in the CPU cache (a third less
    CPU than whole-frame passes on a 768x512 frame); every step is elementwise, so the bits do not depend on
    the banding."""
    out = np.empty(img.shape, np.float16)
    if img.size == 0:
        return out
    normal = normal.reshape(img.shape)
    rows = max(1, NOISE_BAND_VALUES // (img.size // img.shape[0]))
    buf = np.empty((min(rows, img.shape[0]), *img.shape[1:]), np.result_type(img.dtype, np.float32))
    for r0 in range(0, img.shape[0], rows):
        r1 = min(r0 + rows, img.shape[0])
        out[r0:r1] = _noise_band(img[r0:r1], scene.nuisances, cutoff, normal[r0:r1], buf[: r1 - r0])
    return out


def _noise_band(
    img: np.ndarray, nz: Nuisances, cutoff: float, normal: np.ndarray, x: np.ndarray
) -> np.ndarray:
    """add_noise_and_clip on one band, computed in the buffer `x` (img's shape); returns the half values."""
    f = np.float32
    np.maximum(img, 0, out=x)
    x *= f(nz.shot_gain)
    x += f(nz.read_noise**2)
    np.sqrt(x, out=x)
    x *= normal
    x += img
    clipped = x >= f(cutoff)
    if nz.black_level:
        x += f(nz.black_level)
    if nz.quantise_bits:
        top = f(2**nz.quantise_bits - 1)
        np.clip(x, 0.0, f(cutoff), out=x)
        x *= f(1.0 / cutoff)
        if nz.quantise_gamma != 1.0:
            np.power(x, f(1.0 / nz.quantise_gamma), out=x)
        x *= top
        np.rint(x, out=x)
        x *= f(1.0) / top
        if nz.quantise_gamma != 1.0:
            np.power(x, f(nz.quantise_gamma), out=x)
        x *= f(cutoff)
    else:
        x *= f(1.0 / nz.adc_step)
        np.rint(x, out=x)
        x *= f(nz.adc_step)
    if nz.black_level:
        x -= f(nz.black_level)
    np.clip(x, 0.0, f(saturation_value(cutoff)), out=x)
    x[clipped] = f(saturation_value(cutoff))
    return to_half(x)


def _write_clean(
    job: ViewJob, cam: PinholeCamera, index: np.ndarray, radiance: np.ndarray, light: int
) -> None:
    """One clean GT render: noise-free, unclipped float32 object + stand radiance (0 elsewhere), ZIP. Scattered
    straight into the EXR's R, G, B planes (no interleaved image to split)."""
    planes = np.zeros((3, cam.height * cam.width), np.float32)
    planes[:, index] = radiance.T
    path = job.root / CLEAN_TEMPLATE.format(group=job.group, camera=job.camera, light=light)
    named = {c: planes[i].reshape(cam.height, cam.width) for i, c in enumerate("RGB")}
    write_exr_planes(path, named, compression="zip")


def render_view(job: ViewJob) -> ViewRecord:
    """Render and write every frame of one view, its GT mask and its clean frames."""
    start = time.perf_counter()
    cam = job.camera_model
    scene = job.scene
    hits: ViewHits = cast_view(scene, cam.K, cam.R, cam.t, cam.width, cam.height)
    mask = hits.mask()
    write_image(GroundTruth.of(job.root).mask(ViewId(job.group, job.camera)), mask.astype(np.uint8) * 255)
    bg = background_image(cam, scene.nuisances.background)
    bg[mask] = 0.0
    backdrop = None
    if scene.nuisances.backdrop_stops > 0:
        backdrop = make_backdrop(scene, cam, job.camera_index, job.seed, job.saturation)
    gains = (
        np.ones((len(job.light_ids), 3), np.float32)
        if job.light_intensities is None
        else np.asarray(job.light_intensities, np.float32).reshape(len(job.light_ids), 3)
    )
    bulbs: dict[int, int] = {}
    flares: dict[int, float] = {}
    # one seeded pool of standard normals per view; each frame reads a seeded random window of it
    npix = cam.width * cam.height * 3
    pool = None
    if npix <= POOL_MAX_VALUES:
        pool = np.random.default_rng([job.seed, 2, job.group_index, job.camera_index]).standard_normal(
            2 * npix, dtype=np.float32
        )
    flat_index = hits.index
    img = np.empty_like(bg)  # the frame's buffer, reused by every frame of the view
    for lid, sid, p, gain in zip(job.light_ids, job.light_seed_ids, job.light_positions, gains, strict=True):
        radiance = shade(scene, hits, p, scene.light_intensity * gain)
        if lid in job.clean_lights:
            _write_clean(job, cam, flat_index, radiance, lid)
        if backdrop is not None:  # dim interior + lit backdrop; the foreground is overwritten below
            np.add(backdrop_frame(backdrop, p, gain, img.shape[:2], out=img), bg, out=img)
        else:
            np.copyto(img, bg)
        # the foreground shows the object and stand only (0 + radiance: + 0 gives the same bits, -0 to +0)
        scatter_rows(img.reshape(-1, 3), flat_index, radiance + np.float32(0.0))
        strength = add_flare(img, scene, cam, p, scene.light_intensity * gain)
        if strength > 0:
            flares[lid] = strength
        bulb = bulb_pixels(scene, cam, p)
        if bulb is not None:
            img[bulb[0], bulb[1]] = scene.nuisances.bulb_radiance
            bulbs[lid] = int(bulb[0].size)
        frame_rng = np.random.default_rng([job.seed, 3, job.group_index, job.camera_index, sid])
        if pool is not None:
            off = int(frame_rng.integers(npix))
            normal = pool[off : off + npix]
        else:  # large frames: fresh normals per frame (a pool would double the memory)
            normal = frame_rng.standard_normal(npix, dtype=np.float32)
        raw = add_noise_and_clip(img, scene, job.saturation, normal)
        path = job.root / job.path_template.format(group=job.group, camera=job.camera, light=lid)
        write_exr(path, raw, half=True, compression=job.compression, attributes=job.attributes)
    return ViewRecord(job.group, job.camera, int(mask.sum()), bulbs, flares, time.perf_counter() - start)
