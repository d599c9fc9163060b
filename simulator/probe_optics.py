"""The simulated mirror ball's optics: where a light's specular highlight lands on the ball (geometry) and how
the ball, its highlights and the bulbs seen in it form an image (image formation). Pure functions over arrays."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
from scipy import ndimage
from scipy.special import ndtr

from lightstage.cameras import PinholeCamera, pixel_rays
from lightstage.rig import group_transform
from lightstage.simulator.render import background_image, bulb_disc
from lightstage.simulator.scene import SimScene

if TYPE_CHECKING:
    from lightstage.capture.stage import Stage


@dataclass(frozen=True)
class ProbeSettings:
    """The simulated chrome ball, where it is, and how its frames are exposed."""

    radius_m: float = 0.05  # a 4-inch chrome ball
    centre_world: tuple[float, float, float] = (0.07, 0.0, 0.0)  # static in the world, 7 cm off the axis
    yaws_deg: tuple[float, ...] = (0.0, 120.0, 240.0)  # shot in the groups nearest these yaws
    reflectance: float = 0.6  # chrome, neutral
    psf_sigma_px: float = 0.8  # Gaussian PSF (raw pixels)
    highlight_peak: float = (
        2.0  # brightest pixel of a highlight centred on a pixel, light at the stage radius
    )
    ambient_radiance: float = 0.5  # room radiance the ball reflects in the ambient frame (x reflectance)
    supersample: int = 8  # per axis, for the ball's pixel coverage near its silhouette
    psf_window_sigmas: float = 5.0  # highlight spots are integrated over +-this many sigmas


# ---- geometry --------------------------------------------------------------------------------------------------
def specular_point(
    centre: np.ndarray, radius: float, camera_centre: np.ndarray, lights: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Mirror-reflection points on a sphere (Alhazen's problem) for one camera centre and (N, 3) lights.

    Returns (points (N, 3), valid (N,)): x on the sphere whose normal n bisects the directions to the camera and
    to the light, in the plane of camera, centre and light; valid where n faces both (n.(C - x) > 0 and
    n.(p - x) > 0), camera and light are outside the sphere and the light is not exactly behind the ball.
    Solved by bisection on the great-circle angle to machine precision (the root is unique on the arc between
    the directions to the camera and to the light)."""
    c = np.asarray(centre, np.float64)
    C = np.asarray(camera_centre, np.float64)
    P = np.atleast_2d(np.asarray(lights, np.float64))
    a = C - c
    la = float(np.linalg.norm(a))
    e1 = a / la
    b = P - c
    lb = np.linalg.norm(b, axis=-1)
    along = b @ e1
    perp = b - along[:, None] * e1
    lp = np.linalg.norm(perp, axis=-1)
    # any unit vector perpendicular to e1 for lights on the camera-centre line
    helper = np.eye(3)[int(np.argmin(np.abs(e1)))]
    fallback = np.cross(e1, helper)
    fallback /= np.linalg.norm(fallback)
    degenerate = lp <= 1e-12 * np.maximum(lb, 1e-300)
    e2 = np.where(degenerate[:, None], fallback, perp / np.where(degenerate, 1.0, lp)[:, None])
    gamma = np.arctan2(lp, along)  # angle of the light from the camera direction, [0, pi]
    # 2-D coordinates in the plane (e1, e2): camera at (la, 0), light at lb (cos gamma, sin gamma)
    px, py = lb * np.cos(gamma), lb * np.sin(gamma)
    r = float(radius)

    def g(theta: np.ndarray) -> np.ndarray:
        nx, ny = np.cos(theta), np.sin(theta)
        cx, cy = la - r * nx, -r * ny
        qx, qy = px - r * nx, py - r * ny
        cn = np.hypot(cx, cy)
        qn = np.hypot(qx, qy)
        return (nx * cy - ny * cx) / cn + (nx * qy - ny * qx) / qn

    lo = np.zeros_like(gamma)
    hi = gamma.copy()
    for _ in range(64):  # g(lo) >= 0 >= g(hi); 2^-64 of the arc: below float precision
        mid = 0.5 * (lo + hi)
        pos = g(mid) > 0
        lo = np.where(pos, mid, lo)
        hi = np.where(pos, hi, mid)
    theta = 0.5 * (lo + hi)
    n = np.cos(theta)[:, None] * e1 + np.sin(theta)[:, None] * e2
    x = c + r * n
    valid = (
        (la > r)
        & (lb > r)
        & (gamma < np.pi - 1e-9)
        & (np.einsum("ij,ij->i", n, C - x) > 0)
        & (np.einsum("ij,ij->i", n, P - x) > 0)
    )
    return x, valid


def ball_centre_rig(centre_world: np.ndarray, yaw_deg: float, axis: Any) -> np.ndarray:
    """The ball centre in the rig frame of a group (inverse of the group's rig-to-world transform)."""
    Rg, tg = group_transform(yaw_deg, axis)
    return Rg.T @ (np.asarray(centre_world, np.float64) - tg)


def project_point(cam: PinholeCamera, x: np.ndarray) -> tuple[np.ndarray, float]:
    """Continuous pixel coordinates (pixel (i, j) spans [i, i+1) x [j, j+1)) and depth of a world point."""
    pc = cam.R @ np.asarray(x, np.float64) + cam.t
    uv = (cam.K @ pc)[:2] / pc[2]
    return uv, float(pc[2])


def probe_positions(stage: Stage, settings: ProbeSettings = ProbeSettings()) -> list[str]:
    """Group names the probe is shot in: for each of `settings.yaws_deg` the nearest unused group (by nominal
    yaw); as many positions as yaws, or as groups where the stage has fewer (at least 1)."""
    names = [g.name for g in stage.groups]
    yaws = [g.yaw_deg for g in stage.groups]
    chosen: list[str] = []
    for target in settings.yaws_deg or (0.0,):
        free = [i for i in range(len(names)) if names[i] not in chosen]
        if not free:
            break
        i = min(free, key=lambda k: (abs((yaws[k] - target + 180.0) % 360.0 - 180.0), k))
        chosen.append(names[i])
    return chosen


# ---- image formation -------------------------------------------------------------------------------------------
def centred_peak_fraction(sigma: float) -> float:
    """Fraction of a Gaussian spot's energy in the pixel its centre sits in the middle of."""
    return float((2.0 * ndtr(0.5 / sigma) - 1.0) ** 2)


def highlight_energy(
    settings: ProbeSettings,
    camera_centre: np.ndarray,
    point: np.ndarray,
    light: np.ndarray,
    ref_light_distance: float,
) -> float:
    """Integrated pixel energy of a highlight. Far-field convex mirror: the ball sends rho I r^2 / (4 |p - c|^2)
    per steradian towards the camera, which receives it over |C - x|^2; the probe exposure is set so a light at
    `ref_light_distance` (the stage radius) seen on the ball's near side gives a centred peak of
    `settings.highlight_peak`."""
    c = np.asarray(settings.centre_world, np.float64)
    C = np.asarray(camera_centre, np.float64)
    ref_cam = float(np.linalg.norm(C - c)) - settings.radius_m
    e0 = settings.highlight_peak / centred_peak_fraction(settings.psf_sigma_px)
    d_light = float(np.linalg.norm(np.asarray(light) - c))
    d_cam = float(np.linalg.norm(C - np.asarray(point)))
    return e0 * (ref_light_distance / d_light) ** 2 * (ref_cam / d_cam) ** 2


def add_highlight(img: np.ndarray, uv: np.ndarray, energy: float, sigma: float, window: float = 5.0) -> None:
    """Add (in place, all channels) a Gaussian spot of total `energy` centred at continuous pixel coordinates
    `uv`, integrated exactly over each pixel's area, inside +-`window` sigmas."""
    h, w = img.shape[:2]
    u, v = float(uv[0]), float(uv[1])
    c0, c1 = max(int(np.floor(u - window * sigma)), 0), min(int(np.floor(u + window * sigma)) + 1, w)
    r0, r1 = max(int(np.floor(v - window * sigma)), 0), min(int(np.floor(v + window * sigma)) + 1, h)
    if c0 >= c1 or r0 >= r1:
        return
    xs = np.arange(c0, c1 + 1, dtype=np.float64)
    ys = np.arange(r0, r1 + 1, dtype=np.float64)
    wx = np.diff(ndtr((xs - u) / sigma))
    wy = np.diff(ndtr((ys - v) / sigma))
    spot = (energy * np.outer(wy, wx)).astype(np.float32)
    img[r0:r1, c0:c1] += spot[..., None]


def ball_coverage(cam: PinholeCamera, centre: np.ndarray, radius: float, supersample: int = 8) -> np.ndarray:
    """(H, W) float32 fraction of each pixel's area covered by the ball's projection (pinhole): pixels well
    inside the silhouette cone are 1, those within ~1.5 px of it are supersampled `supersample`^2 times."""
    h, w = cam.height, cam.width
    cov = np.zeros((h, w), np.float32)
    C = cam.center
    a = np.asarray(centre, np.float64) - C
    dist = float(np.linalg.norm(a))
    if dist <= radius:
        cov[:] = 1.0
        return cov
    a /= dist
    alpha = float(np.arcsin(radius / dist))
    # image bounding box of the silhouette cone (all of it in front of the camera, or give up on the box)
    helper = np.eye(3)[int(np.argmin(np.abs(a)))]
    e1 = np.cross(a, helper)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(a, e1)
    phi = np.linspace(0, 2 * np.pi, 720, endpoint=False)
    dirs = np.cos(alpha) * a + np.sin(alpha) * (np.cos(phi)[:, None] * e1 + np.sin(phi)[:, None] * e2)
    dc = dirs @ cam.R.T
    if (dc[:, 2] <= 1e-9).any():
        c0, c1, r0, r1 = 0, w, 0, h
    else:
        uv = (dc @ cam.K.T)[:, :2] / dc[:, 2:3]
        c0 = max(int(np.floor(uv[:, 0].min())) - 2, 0)
        c1 = min(int(np.ceil(uv[:, 0].max())) + 3, w)
        r0 = max(int(np.floor(uv[:, 1].min())) - 2, 0)
        r1 = min(int(np.ceil(uv[:, 1].max())) + 3, h)
    if c0 >= c1 or r0 >= r1:
        return cov
    jj, ii = np.mgrid[r0:r1, c0:c1]
    uvc = np.stack([ii + 0.5, jj + 0.5], -1).reshape(-1, 2)
    _, d = pixel_rays(uvc, cam.K, cam.R, cam.t)
    ang = np.arccos(np.clip(d @ a, -1.0, 1.0))
    band = 1.5 / min(cam.K[0, 0], cam.K[1, 1])  # > half a pixel diagonal, as an angle
    box = np.zeros(ang.shape, np.float32)
    box[ang < alpha - band] = 1.0
    edge = np.flatnonzero(np.abs(ang - alpha) <= band)
    if edge.size:
        n = int(supersample)
        offs = (np.arange(n) + 0.5) / n
        sub = np.stack(np.meshgrid(offs, offs, indexing="xy"), -1).reshape(-1, 2)  # (n*n, 2) (du, dv)
        base = np.stack([ii.reshape(-1)[edge], jj.reshape(-1)[edge]], -1).astype(np.float64)
        pts = (base[:, None, :] + sub[None]).reshape(-1, 2)
        _, ds = pixel_rays(pts, cam.K, cam.R, cam.t)
        inside = (ds @ a >= np.cos(alpha)).reshape(edge.size, n * n)
        box[edge] = inside.mean(axis=1)
    cov[r0:r1, c0:c1] = box.reshape(r1 - r0, c1 - c0)
    return cov


def blur_psf(layer: np.ndarray, sigma: float) -> np.ndarray:
    """The PSF (Gaussian, `sigma` px, truncated at 5 sigma) applied to an (H, W) layer; float32."""
    if sigma <= 0:
        return layer.astype(np.float32)
    return ndimage.gaussian_filter(layer.astype(np.float32), sigma, mode="constant", truncate=5.0)


def ball_bulb_pixels(
    cam: PinholeCamera, centre: np.ndarray, radius: float, p: np.ndarray, bulb_radius: float
) -> tuple[np.ndarray, np.ndarray] | None:
    """(rows, cols) of pixels showing the bulb of a light at world `p` that the ball does not hide, or None
    (as render.bulb_pixels, with the ball as the only occluder)."""
    disc_px = bulb_disc(cam, p, bulb_radius)
    if disc_px is None:
        return None
    rows, cols, o, d = disc_px
    # ray-sphere: |o + s d - c|^2 = r^2; occluded where the near hit is in front of the bulb
    oc = o - np.asarray(centre, np.float64)
    bq = np.einsum("ij,ij->i", oc, d)
    disc = bq**2 - (np.einsum("ij,ij->i", oc, oc) - radius**2)
    s_near = -bq - np.sqrt(np.maximum(disc, 0.0))
    dist = float(np.linalg.norm(p - cam.center))
    free = (disc <= 0) | (s_near <= 0) | (s_near > dist)
    if not free.any():
        return None
    return rows[free], cols[free]


@dataclass(frozen=True)
class Highlight:
    """Where one light's mirror highlight is in one view (ground truth)."""

    light: int
    point_world: np.ndarray  # (3,) specular point on the ball
    uv: np.ndarray  # (2,) continuous pixel coordinates of its projection
    visible: bool  # the point faces camera and light, and projects inside the image
    energy: float  # integrated pixel value of the spot (0 when not visible)


def probe_base_images(
    cam: PinholeCamera, scene: SimScene, settings: ProbeSettings
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(coverage (H, W) after the PSF, OLAT base image, ambient image), float32, noise-free. The OLAT base is
    the background with the ball's disc reflecting the dark interior; the ambient image the ball reflecting the
    room radiance."""
    c = np.asarray(settings.centre_world, np.float64)
    raw = ball_coverage(cam, c, settings.radius_m, settings.supersample)
    level = scene.nuisances.background
    bg = background_image(cam, level)
    olat, amb = bg, bg.copy()
    cov = np.zeros_like(raw)
    rows, cols = np.flatnonzero(raw.any(axis=1)), np.flatnonzero(raw.any(axis=0))
    if rows.size:
        # blur and compose only around the ball (the blur of a zero-padded crop is exact)
        m = int(np.ceil(5.0 * settings.psf_sigma_px)) + 1
        r0, r1 = max(rows[0] - m, 0), min(rows[-1] + m + 1, cam.height)
        c0, c1 = max(cols[0] - m, 0), min(cols[-1] + m + 1, cam.width)
        cov[r0:r1, c0:c1] = blur_psf(raw[r0:r1, c0:c1], settings.psf_sigma_px)
        k = cov[r0:r1, c0:c1, None]
        tint = np.array([0.9, 0.95, 1.1], np.float32)
        ball_dark = np.float32(settings.reflectance * level) * tint
        ball_room = np.float32(settings.reflectance * settings.ambient_radiance)
        olat[r0:r1, c0:c1] = bg[r0:r1, c0:c1] * (1.0 - k) + k * ball_dark
        amb[r0:r1, c0:c1] = amb[r0:r1, c0:c1] * (1.0 - k) + k * ball_room
    return cov, olat, amb


def render_probe_olat(
    cam: PinholeCamera,
    light: np.ndarray,
    scene: SimScene,
    settings: ProbeSettings,
    ref_light_distance: float = 1.5,
    base: np.ndarray | None = None,
    light_id: int = 0,
) -> tuple[np.ndarray, Highlight, tuple[np.ndarray, np.ndarray] | None]:
    """Noise-free, unclipped OLAT probe frame (H, W, 3) float32 for one world light position, its highlight
    and the bulb pixels in view (set to the bulb radiance). `base`: probe_base_images' OLAT image (computed if
    None)."""
    if base is None:
        base = probe_base_images(cam, scene, settings)[1]
    img = base.copy()
    c = np.asarray(settings.centre_world, np.float64)
    p = np.asarray(light, np.float64)
    x, valid = specular_point(c, settings.radius_m, cam.center, p[None])
    x = x[0]
    uv, z = project_point(cam, x)
    visible = bool(valid[0]) and z > 0 and 0 <= uv[0] < cam.width and 0 <= uv[1] < cam.height
    energy = 0.0
    if bool(valid[0]) and z > 0:
        energy = highlight_energy(settings, cam.center, x, p, ref_light_distance)
        add_highlight(img, uv, energy, settings.psf_sigma_px, settings.psf_window_sigmas)
    bulb = ball_bulb_pixels(cam, c, settings.radius_m, p, scene.nuisances.bulb_radius)
    if bulb is not None:
        img[bulb[0], bulb[1]] = scene.nuisances.bulb_radiance
    return img, Highlight(light_id, x, uv, visible, energy if visible else 0.0), bulb
