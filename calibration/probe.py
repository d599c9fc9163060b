"""Rays towards the lights from a mirror-ball probe capture (preprocess measured the images: preprocess/probe.py).

A chrome ball of known radius r sits on the turntable at a few positions; every camera photographs it under
each light. In the rig frame the cameras and lights stay put and only the ball moves, so each position's ball
centre is an unknown of the rig frame, found from the ball's outlines: the outline is where the camera's rays
graze the sphere, a cone d . a = cos(beta) about the direction a to the centre, sin(beta) = r / D
(`fit_ball_cone`); the centre is the least-squares point of the cameras' axis rays (`ball_centres`).

A light's highlight is where the ball mirrors it to the camera. The camera ray through it meets the sphere at
x with normal n, and its reflection d - 2 (d.n) n leaves x towards the light: a `LightRay`. The geometry is
done in the camera's own frame with the centre direction from *its* outline, so an error of the camera's
rotation turns the reflected ray by that error only; with the triangulated centre instead, the same error
would move the hit point across a curved mirror and turn the ray by ~2 D / r times as much (~40x here).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from lightstage.calibration.light_rays import LightRay
from lightstage.cameras import camera_center, undistort_pixels
from lightstage.capture.layout import Capture
from lightstage.errors import LightstageError
from lightstage.workdir import WorkDir


@dataclass(frozen=True)
class BallCone:
    """The ball seen by one camera: unit direction to its centre (camera frame), half-angle, outline misfit."""

    axis: np.ndarray
    half_angle: float  # radians
    rms_px: float
    num_points: int

    def distance(self, radius: float) -> float:
        """Distance from the camera centre to the ball centre for a ball of `radius` (same units)."""
        return radius / np.sin(self.half_angle)

    def centre_sigma_px(self) -> float:
        """Std of the centre direction, in pixels: the misfit averaged down over the outline points."""
        return self.rms_px * np.sqrt(2.0 / max(self.num_points, 1))


@dataclass
class ProbeData:
    """What preprocess measured in the probe capture, read back for calibration."""

    radius_m: float
    positions: list[str]
    outlines: dict[tuple[str, str], np.ndarray] = field(default_factory=dict)  # (position, camera) -> (N, 2)
    highlights: dict[tuple[str, str], dict[int, tuple[float, float]]] = field(default_factory=dict)
    missing: int = 0  # (position, camera, light) without a usable highlight
    view_errors: list[str] = field(default_factory=list)


def load_probe(work: WorkDir, capture: Capture) -> ProbeData | None:
    """The capture's probe measurements (None when the capture has no probe); a clear error when preprocess
    has not measured them."""
    from lightstage.capture.probe import load_probe_info
    from lightstage.preprocess.probe import load_view_record

    info = load_probe_info(capture.root)
    if info is None:
        return None
    data = ProbeData(info.radius_m, list(info.positions))
    missing = []
    for pos in info.positions:
        for cam in capture.stage.camera_ids:
            rec = load_view_record(work.probe_view(pos, cam))
            if rec is None:
                missing.append(f"{pos}/{cam}")
                continue
            if rec.error:
                data.view_errors.append(rec.error)
                continue
            data.outlines[pos, cam] = np.asarray(rec.outline, np.float64)
            data.highlights[pos, cam] = {int(k): (v[0], v[1]) for k, v in rec.highlights.items()}
            data.missing += len(rec.missing)
    if missing:
        raise LightstageError(
            f"{work.probe_dir}: no probe measurements for {len(missing)} views ({', '.join(missing[:6])}"
            f"{' ...' if len(missing) > 6 else ''}); run `lightstage preprocess` (again, with this version) first"
        )
    return data


def _camera_dirs(uv: np.ndarray, K: np.ndarray, dist: np.ndarray | None) -> np.ndarray:
    """Unit camera-frame directions through pixel coordinates uv (N, 2) (pixel centres at i + 0.5)."""
    uv = undistort_pixels(np.asarray(uv, np.float64).reshape(-1, 2), K, np.zeros(5) if dist is None else dist)
    d = np.concatenate([uv, np.ones((len(uv), 1))], axis=1) @ np.linalg.inv(K).T
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def fit_ball_cone(outline_uv: np.ndarray, K: np.ndarray, dist: np.ndarray | None = None) -> BallCone:
    """The sphere's cone from its outline: rays d_i with d_i . a = cos(beta), solved as d_i . w = 1 in least
    squares (a = w / |w|, cos(beta) = 1 / |w|), then again without the points 4 MADs off (a post, a bulb)."""
    d = _camera_dirs(outline_uv, K, dist)
    if len(d) < 8:
        raise LightstageError(f"ball outline has {len(d)} points (needs 8)")
    keep = np.ones(len(d), bool)
    for _ in range(2):
        w, *_ = np.linalg.lstsq(d[keep], np.ones(keep.sum()), rcond=None)
        a, cos_b = w / np.linalg.norm(w), 1.0 / np.linalg.norm(w)
        resid = np.arccos(np.clip(d @ a, -1, 1)) - np.arccos(np.clip(cos_b, -1, 1))  # radians
        mad = 1.4826 * np.median(np.abs(resid[keep])) + 1e-12
        keep = np.abs(resid) <= 4 * mad
    rms_px = float(np.sqrt(np.mean(resid[keep] ** 2)) * K[0, 0])
    return BallCone(a, float(np.arccos(np.clip(cos_b, -1, 1))), rms_px, int(keep.sum()))


@dataclass
class BallFit:
    """The balls in a rig frame: per-view cones, per-position centres, and the metric scale the ball implies."""

    cones: dict[tuple[str, str], BallCone]
    centres: dict[str, np.ndarray]  # position -> rig-frame centre
    fit: dict[str, dict[str, float]]  # position -> how well the cameras agree (report)
    scale_ratio: (
        float  # median over views of (r / sin(beta)) / |centre - camera|: 1 when the rig scale is right
    )
    scale_ratio_sigma: float  # its std (spread of the views / sqrt(n))
    errors: list[str] = field(default_factory=list)


def fit_balls(
    data: ProbeData,
    cam_from_rig: dict[str, tuple[np.ndarray, np.ndarray]],
    intrinsics: dict[str, tuple[np.ndarray, np.ndarray]],
) -> BallFit:
    """Cones from the outlines, then per position the centre: the least-squares point of the cameras' axis rays.

    The outline also says how far the ball is (r / sin(beta)) in metres, whatever the rig's units, so the ratio
    of that to the triangulated distance is the rig's metric scale error, measured by a known length (the
    radius) instead of the drawings: `scale_ratio`."""
    cones: dict[tuple[str, str], BallCone] = {}
    errors = []
    for key, outline in data.outlines.items():
        if key[1] not in cam_from_rig:
            continue
        K, dist = intrinsics[key[1]]
        try:
            cones[key] = fit_ball_cone(outline, np.asarray(K, np.float64), np.asarray(dist, np.float64))
        except LightstageError as e:
            errors.append(f"{key[0]}/{key[1]}: {e}")
    centres, fit, ratios = {}, {}, []
    for pos in sorted({p for p, _ in cones}):
        A, b, rays = np.zeros((3, 3)), np.zeros(3), []
        for (p, cam), cone in cones.items():
            if p != pos:
                continue
            R, t = (np.asarray(x, np.float64) for x in cam_from_rig[cam])
            c, d = camera_center(R, t), R.T @ cone.axis
            P = np.eye(3) - np.outer(d, d)
            A += P
            b += P @ c
            rays.append((c, d, cone.distance(data.radius_m)))
        if len(rays) < 2:
            errors.append(f"{pos}: the ball is outlined in {len(rays)} view(s); its centre needs 2")
            continue
        x = np.linalg.solve(A, b)
        miss = [np.linalg.norm((x - c) - ((x - c) @ d) * d) for c, d, _ in rays]
        ratio = [D / np.linalg.norm(x - c) for c, _, D in rays]
        ratios += ratio
        centres[pos] = x
        fit[pos] = {
            "cameras": len(rays),
            "ray_rms_mm": round(1000 * float(np.sqrt(np.mean(np.square(miss)))), 4),
            "scale_ratio": round(float(np.median(ratio)), 7),
        }
    if ratios:
        k = float(np.median(ratios))
        k_sigma = 1.4826 * float(np.median(np.abs(np.subtract(ratios, k)))) / np.sqrt(len(ratios))
    else:
        k, k_sigma = 1.0, np.inf
    return BallFit(cones, centres, fit, k, k_sigma, errors)


def _reflect(d: np.ndarray, c: np.ndarray, r: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Camera-frame rays d (N, 3) (unit, from the origin) on spheres (c (N, 3), r): (hit points, reflected unit
    directions, hit mask: False where a ray misses its sphere; its outputs are then meaningless)."""
    dc = np.einsum("ij,ij->i", d, c)
    disc = dc**2 - (np.einsum("ij,ij->i", c, c) - r * r)
    x = (dc - np.sqrt(np.clip(disc, 0.0, None)))[:, None] * d
    n = (x - c) / r
    refl = d - 2.0 * np.einsum("ij,ij->i", d, n)[:, None] * n
    return x, refl / np.linalg.norm(refl, axis=1, keepdims=True), disc >= 0


@dataclass
class _Highlights:
    """Every usable highlight as arrays (one row each), with its view's pose and sphere."""

    views: list[tuple[str, str]]  # (position, camera) per view index
    view: np.ndarray  # (N,) view index
    light: np.ndarray  # (N,) light index
    d: np.ndarray  # (N, 3) camera-frame unit ray through the highlight
    R: np.ndarray  # (N, 3, 3) camera-from-rig rotation
    axis: np.ndarray  # (N, 3) camera-frame direction to the ball centre (the view's own outline)
    centre: np.ndarray  # (N, 3) rig-frame ball centre of the view's position
    D0: np.ndarray  # (V,) camera-to-ball distance (metres) per view: triangulated x the ball's scale
    sigma: np.ndarray  # (N,) angular std of the reflected ray (pixel and rotation errors)
    missed: int = 0  # highlights whose ray misses the ball


def _highlights(
    data: ProbeData,
    balls: BallFit,
    cam_from_rig: dict[str, tuple[np.ndarray, np.ndarray]],
    intrinsics: dict[str, tuple[np.ndarray, np.ndarray]],
    pixel_sigma: float,
    rotation_sigma_deg: float,
) -> _Highlights:
    """Gather the highlights of the views whose ball is fitted; each ray's std is the pixel std (highlight and
    outline centre) through the mirror's local magnification (numerically: 0.1 px steps), with the rotation std."""
    r, k = data.radius_m, balls.scale_ratio
    views = sorted(v for v in balls.cones if v[0] in balls.centres)
    rows: dict[str, list] = {n: [] for n in ("view", "light", "d", "R", "axis", "centre", "sigma")}
    D0 = np.zeros(len(views))
    missed = 0
    for vi, (pos, cam) in enumerate(views):
        cone = balls.cones[pos, cam]
        R, t = (np.asarray(x, np.float64) for x in cam_from_rig[cam])
        K, dist = (np.asarray(x, np.float64) for x in intrinsics[cam])
        D0[vi] = k * np.linalg.norm(balls.centres[pos] - camera_center(R, t))
        hl = sorted(data.highlights.get((pos, cam), {}).items())
        if not hl:
            continue
        uv = np.array([u for _, u in hl], np.float64)
        dirs = [_camera_dirs(uv + off, K, dist) for off in ((0, 0), (0.1, 0), (0, 0.1))]
        c = np.broadcast_to(D0[vi] * cone.axis, dirs[0].shape)
        (_, refl, ok), (_, ru, oku), (_, rv, okv) = (_reflect(d, c, r) for d in dirs)
        ok &= oku & okv
        missed += int((~ok).sum())
        gain = np.maximum(np.linalg.norm(ru - refl, axis=1), np.linalg.norm(rv - refl, axis=1)) / 0.1
        sigma_px = np.hypot(pixel_sigma, cone.centre_sigma_px())
        sigma = np.hypot(gain * sigma_px, np.deg2rad(rotation_sigma_deg))
        n = int(ok.sum())
        rows["view"].append(np.full(n, vi))
        rows["light"].append(np.array([li for li, _ in hl])[ok])
        rows["d"].append(dirs[0][ok])
        rows["R"].append(np.broadcast_to(R, (n, 3, 3)))
        rows["axis"].append(np.broadcast_to(cone.axis, (n, 3)))
        rows["centre"].append(np.broadcast_to(balls.centres[pos], (n, 3)))
        rows["sigma"].append(sigma[ok])
    if not rows["view"]:
        z3 = np.zeros((0, 3))
        return _Highlights(
            views,
            np.zeros(0, int),
            np.zeros(0, int),
            z3,
            np.zeros((0, 3, 3)),
            z3,
            z3,
            D0,
            np.zeros(0),
            missed,
        )
    cat = {n: np.concatenate(v) for n, v in rows.items()}
    return _Highlights(views, D0=D0, missed=missed, **cat)


def _rig_rays(h: _Highlights, D: np.ndarray, r: float, k: float) -> tuple[np.ndarray, np.ndarray]:
    """(origins, unit directions) in the rig frame of every highlight's reflected ray for view distances D."""
    c_cam = D[h.view][:, None] * h.axis
    x, refl, _ = _reflect(h.d, c_cam, r)
    # The hit point relative to the ball centre (length r), in rig units, from the common triangulated centre:
    # every camera's rays start on one sphere.
    origin = h.centre + np.einsum("nji,nj->ni", h.R, x - c_cam) / k
    return origin, np.einsum("nji,nj->ni", h.R, refl)


def refine_distances(
    h: _Highlights, nominal: np.ndarray, r: float, k: float, distance_sigma_m: float, light_sigma_m: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-view camera-to-ball distances and light positions fitted together (sparse least squares).

    A view's distance sets where its rays meet the curved mirror, so an error of 0.05 mm (the cameras' relative
    positions after SfM are ~0.2 mm off) turns its reflected rays by ~1 mrad; but it turns all of that view's
    rays in one pattern, which the other views' rays towards the same lights pin down. Residuals: each ray's
    miss of its light (two components across the ray, in its angular stds), the distance changes (prior
    `distance_sigma_m`) and the lights' shifts from nominal (`light_sigma_m` per axis). Returns (distances,
    lights (L, 3), posterior std of each distance)."""
    from scipy.optimize import least_squares
    from scipy.sparse import coo_matrix

    V, L, N = len(h.D0), len(nominal), len(h.view)
    _, d0 = _rig_rays(h, h.D0, r, k)
    a = np.cross(d0, np.where(np.abs(d0[:, 2:3]) < 0.9, [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]))
    a /= np.linalg.norm(a, axis=1, keepdims=True)
    b = np.cross(d0, a)

    def residuals(x: np.ndarray) -> np.ndarray:
        dD, P = x[:V], x[V:].reshape(L, 3)
        o, dr = _rig_rays(h, h.D0 + dD, r, k)
        v = P[h.light] - o
        perp = v - np.einsum("ij,ij->i", v, dr)[:, None] * dr
        scale = 1.0 / (np.linalg.norm(v, axis=1) * h.sigma)
        return np.concatenate(
            [
                np.einsum("ij,ij->i", perp, a) * scale,
                np.einsum("ij,ij->i", perp, b) * scale,
                dD / distance_sigma_m,
                ((P - nominal) / light_sigma_m).ravel(),
            ]
        )

    obs = np.arange(N)
    rows = np.concatenate([obs, obs + N] + [np.tile(obs, 3) + off for off in (0, N)])
    cols = np.concatenate([h.view, h.view] + [np.concatenate([V + 3 * h.light + j for j in range(3)])] * 2)
    rows = np.concatenate([rows, 2 * N + np.arange(V + 3 * L)])
    cols = np.concatenate([cols, np.arange(V + 3 * L)])
    sparsity = coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(2 * N + V + 3 * L, V + 3 * L)).tocsr()
    x0 = np.concatenate([np.zeros(V), nominal.ravel()])
    sol = least_squares(residuals, x0, jac_sparsity=sparsity, x_scale="jac", method="trf")
    J = sol.jac.toarray() if hasattr(sol.jac, "toarray") else np.asarray(sol.jac)
    cov = np.linalg.pinv(J.T @ J)
    return h.D0 + sol.x[:V], sol.x[V:].reshape(L, 3), np.sqrt(np.clip(np.diag(cov)[:V], 0.0, None))


def probe_rays(
    data: ProbeData,
    cam_from_rig: dict[str, tuple[np.ndarray, np.ndarray]],
    intrinsics: dict[str, tuple[np.ndarray, np.ndarray]],
    pixel_sigma: float = 0.01,
    rotation_sigma_deg: float = 0.01,
    distance_sigma_mm: float = 0.2,
    nominal_lights: np.ndarray | None = None,
    light_sigma_mm: float = 3.0,
    keep_distance_sigma: bool = False,
) -> tuple[list[LightRay], dict]:
    """Every highlight as a ray towards its light in the rig frame of `cam_from_rig`, and a report.

    `intrinsics`: camera -> raw-resolution (K, distortion). The sphere each camera sees lies along its own
    outline's axis, at the triangulated distance times the ball's `scale_ratio`. The normals are sensitive to
    that distance (0.05 mm turns a ray by ~1 mrad on a 5 cm ball), and the cameras' relative positions after SfM
    are only good to `distance_sigma_mm`: with `nominal_lights` given, the distances are refined together with
    the lights (`refine_distances`) and the rays use them; given those, each light's least-squares point is the
    joint solution, so the distances' remaining uncertainty is left out of the rays' stds unless
    `keep_distance_sigma` (for uses that need each ray's full uncertainty, such as the gauge; without refinement
    it is always in, from `distance_sigma_mm`)."""
    r = data.radius_m
    balls = fit_balls(data, cam_from_rig, intrinsics)
    k = balls.scale_ratio
    h = _highlights(data, balls, cam_from_rig, intrinsics, pixel_sigma, rotation_sigma_deg)
    D, D_sigma = h.D0, np.full(len(h.D0), distance_sigma_mm / 1000.0)
    refined = nominal_lights is not None and len(h.view) > 0
    D_post = D_sigma
    if refined:
        # Given the refined distances, each light's least-squares point of these rays is the joint solution;
        # the distances' remaining uncertainty (reported) is shared by all rays of a view, so it is not added
        # to the rays as if it were independent.
        D, _, D_post = refine_distances(
            h,
            np.asarray(nominal_lights, np.float64),
            r,
            k,
            distance_sigma_mm / 1000.0,
            light_sigma_mm / 1000.0,
        )
        D_sigma = D_post if keep_distance_sigma else np.zeros(len(D))
    origin, direction = _rig_rays(h, D, r, k)
    # The distance's remaining uncertainty, through each ray's sensitivity to it (0.01 mm step).
    _, farther = _rig_rays(h, D + 1e-5, r, k)
    gain_d = np.linalg.norm(farther - direction, axis=1) / 1e-5  # radians per metre
    sigma = np.hypot(h.sigma, gain_d * D_sigma[h.view])
    rays = [
        LightRay(int(li), origin[i], direction[i], float(sigma[i]), f"probe {h.views[v][0]}/{h.views[v][1]}")
        for i, (li, v) in enumerate(zip(h.light, h.view, strict=True))
    ]
    cones = balls.cones.values()
    report = {
        "radius_m": r,
        "positions": data.positions,
        "ball_centres_rig_m": {p: [round(float(v), 6) for v in x] for p, x in balls.centres.items()},
        "ball_centre_fit": balls.fit,
        "scale_ratio": round(k, 7),
        "scale_ratio_sigma": round(balls.scale_ratio_sigma, 7),
        "outline_rms_px": {
            "mean": round(float(np.mean([c.rms_px for c in cones])), 4) if cones else None,
            "max": round(float(np.max([c.rms_px for c in cones])), 4) if cones else None,
        },
        "distances_refined": refined,
        "distance_change_mm": {
            "rms": round(1000 * float(np.sqrt(np.mean((D - h.D0) ** 2))), 4) if len(D) else None,
            "max": round(1000 * float(np.max(np.abs(D - h.D0))), 4) if len(D) else None,
        },
        "distance_sigma_mm": round(1000 * float(np.mean(D_post)), 4) if len(D) else None,
        "views": len(balls.cones),
        "view_errors": (data.view_errors + balls.errors)[:20],
        "rays": len(rays),
        "highlights_off_ball": h.missed,
        "highlights_missing": data.missing,
    }
    return rays, report
