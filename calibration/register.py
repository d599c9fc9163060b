"""Registration of a recovered camera rig to the stage's world frame: similarity gauge, turntable axis and yaws.

SfM recovers the rig (camera poses relative to each other) and one rig pose per turntable group, in a frame
known only up to a similarity. The world frame of the conventions is fixed here (the gauge):

1. Metric scale, rotation and origin come from the similarity that best puts the recovered rig onto the stage's
   nominal rig (stage.yaml): the Umeyama fit of the camera centres, refined (`fit_gauge`) to also match the
   nominal camera orientations given the mounting tolerances (centres alone pin the rotation poorly). This
   defines the *stage rig frame* of the estimate; lights are locked to it at their nominal rig-frame positions.
2. The world frame is the stage rig frame of the reference group (the first group) placed at that group's
   nominal yaw about the estimated turntable axis; for a yaw-0 reference group (every preset) the world frame
   simply *is* the reference group's rig frame (origin at the sphere centre, +z the nominal up).
3. The turntable axis (unit direction + the point on it closest to the origin) and per-group yaws are fitted to
   the recovered rig-to-world motions of the other groups relative to the reference group.

Camera poses and light positions are taken from each group's *recovered* rig pose (not the fitted turntable
model); the model's misfit is reported so a wobbly turntable is visible.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from lightstage.errors import LightstageError
from lightstage.rig import TurntableAxis, group_transform


@dataclass(frozen=True)
class Similarity:
    """x' = scale * R x + t."""

    scale: float
    R: np.ndarray
    t: np.ndarray

    def apply(self, x: np.ndarray) -> np.ndarray:
        """Map (..., 3) points."""
        return self.scale * np.asarray(x) @ self.R.T + self.t

    def inverse(self) -> Similarity:
        Ri = self.R.T
        return Similarity(1.0 / self.scale, Ri, -(Ri @ self.t) / self.scale)

    def compose(self, other: Similarity) -> Similarity:
        """self after other: x -> self(other(x))."""
        return Similarity(self.scale * other.scale, self.R @ other.R, self.scale * self.R @ other.t + self.t)

    def transform_pose(self, R_cw: np.ndarray, t_cw: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """World-to-camera pose expressed in the mapped frame (metric units follow the scale)."""
        R_new = np.asarray(R_cw) @ self.R.T
        t_new = self.scale * np.asarray(t_cw) - R_new @ self.t
        return R_new, t_new


def umeyama(src: np.ndarray, dst: np.ndarray, with_scale: bool = True) -> Similarity:
    """Least-squares similarity mapping points `src` (N, 3) onto `dst` (N, 3) (Umeyama 1991)."""
    src = np.asarray(src, dtype=np.float64)
    dst = np.asarray(dst, dtype=np.float64)
    if src.shape != dst.shape or src.ndim != 2 or src.shape[1] != 3 or len(src) < 3:
        raise LightstageError(
            f"similarity fit needs >= 3 matching 3D points, got {src.shape} and {dst.shape}"
        )
    mu_s, mu_d = src.mean(0), dst.mean(0)
    xs, xd = src - mu_s, dst - mu_d
    cov = xd.T @ xs / len(src)
    U, D, Vt = np.linalg.svd(cov)
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[2, 2] = -1.0
    R = U @ S @ Vt
    var_s = (xs**2).sum() / len(src)
    if var_s <= 0:
        raise LightstageError("similarity fit: source points are all identical")
    scale = float(np.trace(np.diag(D) @ S) / var_s) if with_scale else 1.0
    return Similarity(scale, R, mu_d - scale * R @ mu_s)


def fit_gauge(
    src: np.ndarray,
    dst: np.ndarray,
    src_rot: np.ndarray | None = None,
    dst_rot: np.ndarray | None = None,
    position_sigma: float = 0.003,
    rotation_sigma_deg: float = 0.2,
    src_extra: np.ndarray | None = None,
    dst_extra: np.ndarray | None = None,
    extra_sigma: float | np.ndarray = 0.003,
    scale_prior: tuple[float, float] | None = None,
) -> Similarity:
    """Maximum-likelihood similarity x -> s R x + t putting a recovered rig onto the nominal (drawn) one.

    Points `src` (N, 3) should land on `dst` (position error `position_sigma` per axis, metres after mapping);
    world-to-camera rotations `src_rot` (N, 3, 3), which become src_rot R^T, should match `dst_rot` (per-axis
    error `rotation_sigma_deg`); optional extra points (e.g. observed lights) likewise with `extra_sigma`: one
    sigma, one per point (N,), or per-point (N, 3, 3) square-root information matrices L (residual L (S x - y),
    for points known only across a ray). `scale_prior` = (s, relative std): a scale measured independently
    (e.g. by a ball of known radius), which the drawings' positions can only estimate to their tolerance over
    the rig's size. Starts from the Umeyama fit of the points; with positions alone it is that fit.
    """
    from scipy.optimize import least_squares

    S0 = umeyama(src, dst)
    use_rot = src_rot is not None and dst_rot is not None and rotation_sigma_deg > 0
    use_extra = src_extra is not None and dst_extra is not None and len(src_extra) > 0
    use_scale = scale_prior is not None
    if not use_rot and not use_extra and not use_scale:
        return S0
    src, dst = np.asarray(src, float), np.asarray(dst, float)
    sig_r = np.deg2rad(rotation_sigma_deg)
    if use_extra:
        src_extra, dst_extra = np.asarray(src_extra, float), np.asarray(dst_extra, float)
        sig = np.asarray(extra_sigma, float)
        if sig.ndim == 3:
            if sig.shape != (len(src_extra), 3, 3):
                raise LightstageError(
                    f"fit_gauge: extra_sigma has shape {sig.shape}, expected ({len(src_extra)}, 3, 3)"
                )
            L_extra = sig
        else:
            L_extra = np.eye(3) / np.broadcast_to(sig, (len(src_extra),))[:, None, None]

    def similarity(x: np.ndarray) -> Similarity:
        return Similarity(
            S0.scale * np.exp(x[3]), Rotation.from_rotvec(x[:3]).as_matrix() @ S0.R, S0.t + x[4:]
        )

    def residuals(x: np.ndarray) -> np.ndarray:
        S = similarity(x)
        out = [((S.apply(src) - dst) / position_sigma).ravel()]
        if use_rot:
            err = Rotation.from_matrix(np.asarray(src_rot) @ S.R.T @ np.transpose(dst_rot, (0, 2, 1)))
            out.append(err.as_rotvec().ravel() / sig_r)
        if use_extra:
            out.append(np.einsum("nij,nj->ni", L_extra, S.apply(src_extra) - dst_extra).ravel())
        if use_scale:
            out.append(np.array([np.log(S.scale / scale_prior[0]) / scale_prior[1]]))
        return np.concatenate(out)

    sol = least_squares(residuals, np.zeros(7), x_scale=np.r_[np.full(3, 1e-3), 1e-3, np.full(3, 1e-3)])
    return similarity(sol.x)


@dataclass(frozen=True)
class Rigid:
    """Rig-to-world motion x_w = R x_r + t (metres)."""

    R: np.ndarray
    t: np.ndarray


@dataclass(frozen=True)
class TurntableFit:
    """Fitted turntable axis and yaws, with how well a pure rotation explains each group's motion."""

    axis: TurntableAxis
    yaws_deg: dict[str, float]
    rotation_misfit_deg: dict[str, float]  # angle between recovered and modelled rig rotation
    translation_misfit_m: dict[str, float]  # distance between recovered and modelled rig translation


def fit_turntable(
    rig_to_world: dict[str, Rigid],
    reference: str,
    reference_yaw_deg: float = 0.0,
    nominal_direction: np.ndarray = (0.0, 0.0, 1.0),
) -> TurntableFit:
    """Fit the turntable axis and yaws to rig-to-world motions; yaws are relative to `reference` plus its yaw.

    Group g's motion relative to the reference, M_g = T_g T_ref^-1, is a rotation about the axis by
    psi_g - psi_ref. The direction is the angle-weighted mean of the relative rotation axes (oriented like
    `nominal_direction`), the point solves (I - R_g) a = t_g in least squares (closest to the origin).
    """
    nominal_direction = np.asarray(nominal_direction, dtype=np.float64)
    nominal_direction /= np.linalg.norm(nominal_direction)
    ref = rig_to_world[reference]
    rel: dict[str, Rigid] = {}
    for g, T in rig_to_world.items():
        R = T.R @ ref.R.T
        rel[g] = Rigid(R, T.t - R @ ref.t)
    others = [g for g in rel if g != reference]
    if not others:
        direction = nominal_direction
    else:
        acc = np.zeros(3)
        for g in others:
            rv = Rotation.from_matrix(rel[g].R).as_rotvec()
            if rv @ nominal_direction < 0:
                rv = -rv  # same rotation read the other way round: axis like the nominal, angle > 180 deg
            acc += rv
        if np.linalg.norm(acc) < 1e-9:
            raise LightstageError("turntable fit: the groups do not rotate relative to each other")
        direction = acc / np.linalg.norm(acc)
    # Axis point: (I - R_g) a = t_g for every group, plus d . a = 0 (the point closest to the origin).
    rows = [direction[None, :]]
    rhs = [np.zeros(1)]
    for g in others:
        rows.append(np.eye(3) - rel[g].R)
        rhs.append(rel[g].t)
    a, *_ = np.linalg.lstsq(np.concatenate(rows), np.concatenate(rhs), rcond=None)
    yaws: dict[str, float] = {}
    rot_misfit: dict[str, float] = {}
    trans_misfit: dict[str, float] = {}
    axis0 = TurntableAxis(tuple(map(float, direction)), tuple(map(float, a)))
    for g, M in rel.items():
        q = Rotation.from_matrix(M.R).as_quat()  # x y z w
        angle = 2.0 * np.arctan2(q[:3] @ direction, q[3])
        rel_yaw = float(np.rad2deg(angle))
        yaw = (reference_yaw_deg + rel_yaw) % 360.0
        if g == reference:
            yaw = float(reference_yaw_deg) % 360.0
        yaws[g] = yaw
        Rm, tm = group_transform(rel_yaw if g != reference else 0.0, axis0)
        rot_misfit[g] = float(np.rad2deg(Rotation.from_matrix(Rm.T @ M.R).magnitude()))
        trans_misfit[g] = float(np.linalg.norm(tm - M.t))
    return TurntableFit(axis0, yaws, rot_misfit, trans_misfit)


@dataclass(frozen=True)
class Registration:
    """The recovered rig expressed in the world frame of the conventions."""

    cam_from_rig: dict[str, Rigid]  # camera id -> stage-rig-to-camera (x_c = R x_r + t), metres
    rig_to_world: dict[str, Rigid]  # group -> stage-rig-to-world for that group
    turntable: TurntableFit
    rig_similarity: Similarity  # recovered rig frame -> stage rig frame (scale = metres per SfM unit)
    world_from_sfm: Similarity  # recovered (SfM) world -> world frame of the conventions
    rig_fit_rms_m: float  # RMS distance of the aligned rig camera centres to the nominal ones

    def camera_pose(self, group: str, camera: str) -> tuple[np.ndarray, np.ndarray]:
        """World-to-camera (R, t) of a view."""
        C = self.cam_from_rig[camera]
        T = self.rig_to_world[group]
        R = C.R @ T.R.T
        return R, C.t - R @ T.t

    def light_positions(self, group: str, rig_positions: np.ndarray) -> np.ndarray:
        """(L, 3) world positions of lights at rig-frame positions `rig_positions` for a group."""
        T = self.rig_to_world[group]
        return np.asarray(rig_positions) @ T.R.T + T.t


def register_rig(
    sensor_from_rig: dict[str, tuple[np.ndarray, np.ndarray]],
    rig_from_world: dict[str, tuple[np.ndarray, np.ndarray]],
    nominal_centres: dict[str, np.ndarray],
    group_order: list[str],
    reference_yaw_deg: float = 0.0,
    nominal_direction: np.ndarray = (0.0, 0.0, 1.0),
    nominal_rotations: dict[str, np.ndarray] | None = None,
    position_sigma_m: float = 0.003,
    rotation_sigma_deg: float = 0.0,
    extra_points: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
    scale_prior: tuple[float, float] | None = None,
) -> Registration:
    """Register a recovered rig (SfM frame, arbitrary similarity) to the world frame (see the module doc).

    `sensor_from_rig[c]` = (R, t) of camera c in the recovered rig frame; `rig_from_world[g]` = (R, t) of the
    recovered rig for group g; `nominal_centres[c]` = nominal rig-frame camera centre (metres).
    `group_order[0]` is the reference group. With `nominal_rotations` (camera id -> nominal rig-frame
    world-to-camera rotation) and `rotation_sigma_deg` > 0 the gauge also fits the camera orientations
    (`fit_gauge`); `extra_points` = (recovered rig-frame points, nominal positions, sigmas in metres or
    square-root information matrices, see `fit_gauge`) adds further nominal points (observed lights);
    `scale_prior` = (metres per recovered unit, relative std) a measured scale (`fit_gauge`).
    """
    cams = [c for c in nominal_centres if c in sensor_from_rig]
    if len(cams) < 3:
        raise LightstageError(f"registration needs >= 3 recovered cameras, got {len(cams)}")
    src = np.stack([-sensor_from_rig[c][0].T @ sensor_from_rig[c][1] for c in cams])
    dst = np.stack([np.asarray(nominal_centres[c], float) for c in cams])
    src_rot = dst_rot = None
    if nominal_rotations is not None and rotation_sigma_deg > 0:
        src_rot = np.stack([sensor_from_rig[c][0] for c in cams])
        dst_rot = np.stack([np.asarray(nominal_rotations[c], float) for c in cams])
    ex_src, ex_dst, ex_sig = extra_points if extra_points is not None else (None, None, 1.0)
    # recovered rig -> stage rig
    S_rig = fit_gauge(
        src, dst, src_rot, dst_rot, position_sigma_m, rotation_sigma_deg, ex_src, ex_dst, ex_sig, scale_prior
    )
    rig_rms = float(np.sqrt(((S_rig.apply(src) - dst) ** 2).sum(1).mean()))
    S_rig_inv = S_rig.inverse()
    # Stage-rig-to-camera in metres.
    cam_from_rig = {c: Rigid(*S_rig.transform_pose(R_s, t_s)) for c, (R_s, t_s) in sensor_from_rig.items()}
    groups = [g for g in group_order if g in rig_from_world]
    if not groups or groups[0] != group_order[0]:
        raise LightstageError(f"registration: the reference group {group_order[0]!r} was not recovered")
    ref = groups[0]
    # SfM world -> stage rig frame of the reference group (a similarity): x_r = S_rig(Q_ref x_w + s_ref).
    Q0, s0 = rig_from_world[ref]
    world_from_sfm = S_rig.compose(Similarity(1.0, np.asarray(Q0), np.asarray(s0)))
    # Each group's stage-rig-to-world in that provisional world frame.
    provisional = {}
    for g in groups:
        Q, s = rig_from_world[g]
        sfm_from_rig = Similarity(1.0, np.asarray(Q), np.asarray(s)).inverse().compose(S_rig_inv)
        M = world_from_sfm.compose(sfm_from_rig)  # scale cancels to 1
        provisional[g] = Rigid(M.R, M.t)
    fit = fit_turntable(provisional, ref, 0.0, nominal_direction)
    # Place the reference group at its nominal yaw about the fitted axis (identity for a yaw-0 reference).
    R_ref, t_ref = group_transform(reference_yaw_deg, fit.axis)
    place = Similarity(1.0, R_ref, t_ref)
    axis = TurntableAxis(
        tuple(map(float, R_ref @ np.asarray(fit.axis.direction))),
        tuple(map(float, place.apply(np.asarray(fit.axis.point)))),
    )
    world_from_sfm = place.compose(world_from_sfm)
    rig_to_world = {g: Rigid(R_ref @ T.R, R_ref @ T.t + t_ref) for g, T in provisional.items()}
    fit = TurntableFit(
        axis,
        {g: (y + reference_yaw_deg) % 360.0 for g, y in fit.yaws_deg.items()},
        fit.rotation_misfit_deg,
        fit.translation_misfit_m,
    )
    return Registration(cam_from_rig, rig_to_world, fit, S_rig, world_from_sfm, rig_rms)
