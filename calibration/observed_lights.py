"""Rig-frame light positions from what observed the lights in the calibrate stage: bulbs seen directly
(bulbs.py) and the mirror-ball probe (probe.py), optionally joining the gauge fit (`gauge_with_lights`)."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from lightstage.calibration.config import CalibrateConfig
from lightstage.capture.layout import Capture
from lightstage.workdir import WorkDir


def gauge_with_lights(
    register: Callable[[tuple | None], Any],
    src: np.ndarray,
    lights: list[int],
    nominal: np.ndarray,
    sqrt_info: np.ndarray,
    max_sigma: float,
) -> tuple[Any, list[int], dict[str, float]]:
    """Refit the gauge with observed lights as extra points (`register(extra_points)` -> Registration); a light
    whose weighted residual |L (S x - nominal)| exceeds `max_sigma` (a wrong disc, or a camera SfM got wrong) is
    dropped and the gauge refitted once. Returns (registration, lights used, {dropped light: residual})."""
    src, nominal, sqrt_info = np.asarray(src), np.asarray(nominal), np.asarray(sqrt_info)
    reg = register((src, nominal, sqrt_info))
    resid = np.linalg.norm(
        np.einsum("nij,nj->ni", sqrt_info, reg.rig_similarity.apply(src) - nominal), axis=1
    )
    bad = resid > max_sigma
    if not bad.any():
        return reg, list(lights), {}
    keep = ~bad
    rejected = {str(lights[i]): round(float(resid[i]), 2) for i in np.flatnonzero(bad)}
    reg = register((src[keep], nominal[keep], sqrt_info[keep]) if keep.any() else None)
    return reg, [lt for lt, k in zip(lights, keep, strict=True) if k], rejected


def _rig_poses(reg) -> dict[str, tuple[np.ndarray, np.ndarray]]:  # noqa: ANN001 - register.Registration
    """Camera id -> (R, t) camera-from-rig of a registration (what the bulb functions take)."""
    return {c: (T.R, T.t) for c, T in reg.cam_from_rig.items()}


def observe_lights(
    work: WorkDir,
    capture: Capture,
    config: CalibrateConfig,
    intr: dict,
    register: Callable[[tuple | None, tuple | None], Any],
    reg: Any,
    log: Callable[[str], None],
) -> tuple[dict[str, Any], dict[str, Any] | None]:
    """Rig-frame light positions from what observed the lights: bulbs seen directly (`bulbs.py`) and the
    mirror-ball probe (`probe.py`); with `lights_in_gauge` the observed lights first join the gauge fit.
    Returns (report with "_result": (registration, rig-frame lights, lights in the gauge), probe report)."""
    from lightstage.calibration.bulbs import bulb_rays, find_bulbs, processed_intrinsics
    from lightstage.calibration.light_rays import gauge_points, locate_lights
    from lightstage.calibration.probe import fit_balls, load_probe, probe_rays

    stage = capture.stage
    nominal = stage.light_positions_rig()
    intr_K = {c: K for c, (K, _) in intr.items()}
    K_proc = processed_intrinsics(stage, intr_K)
    light_sigma = config.light_prior_sigma_mm / 1000.0
    found = find_bulbs(work, capture, _rig_poses(reg), nominal, intr_K) if config.observe_bulbs else None
    probe = load_probe(work, capture) if config.use_probe else None

    def rays_of(reg: Any, for_gauge: bool = False) -> tuple[list, dict[str, Any] | None]:
        rays = bulb_rays(found.sightings, _rig_poses(reg), K_proc, config.bulb_pixel_sigma) if found else []
        if probe is None:
            return rays, None
        more, report = probe_rays(
            probe,
            _rig_poses(reg),
            intr,
            config.probe_pixel_sigma,
            config.probe_rotation_sigma_deg,
            config.probe_distance_sigma_mm,
            nominal_lights=nominal if config.probe_refine_distances else None,
            light_sigma_mm=config.light_prior_sigma_mm,
            keep_distance_sigma=for_gauge,
        )
        if scale_prior is not None:
            report["gauge_scale_prior"] = {
                "metres_per_sfm_unit": scale_prior[0],
                "relative_sigma": scale_prior[1],
            }
        return rays + more, report

    scale_prior = None
    if probe is not None and config.probe_scale:
        # The ball's known radius measures the rig's metric scale far better than the drawings' camera
        # positions can (their tolerance over the rig's size): refit the gauge with it.
        balls = fit_balls(probe, _rig_poses(reg), intr)
        if np.isfinite(balls.scale_ratio_sigma) and len(balls.cones) >= 3:
            rel = float(
                np.hypot(
                    balls.scale_ratio_sigma / balls.scale_ratio,
                    config.probe_radius_sigma_mm / 1e3 / probe.radius_m,
                )
            )
            scale_prior = (reg.rig_similarity.scale * balls.scale_ratio, max(rel, 1e-7))
            reg = register(None, scale_prior)
            log(
                f"probe: the ball's radius puts the rig's scale {1e3 * (balls.scale_ratio - 1):+.3f} per mille off "
                f"the drawings' fit (+- {1e3 * rel:.3f})"
            )

    def register_lights(extra_points: tuple | None) -> Any:
        return register(extra_points, scale_prior)

    rays, probe_report = rays_of(reg, for_gauge=True)
    gauge_lights: list[int] = []
    gauge_rejected: dict[str, float] = {}
    if config.lights_in_gauge and rays:
        # Observed lights are nominal points of the rig too: refit the gauge with them (their points, found in
        # the first fit's frame, are mapped back to the SfM rig frame the gauge starts from), then redo the rays.
        gauge_lights, pts, nom, sqrt_info = gauge_points(rays, nominal, mount_sigma_m=light_sigma)
        reg, gauge_lights, gauge_rejected = gauge_with_lights(
            register_lights,
            reg.rig_similarity.inverse().apply(pts),
            gauge_lights,
            nom,
            sqrt_info,
            config.light_gauge_max_sigma,
        )
    rays, probe_report = rays_of(reg)
    est = locate_lights(rays, nominal, prior_sigma_m=light_sigma)
    by_bulb = {li for li, src in est.sources.items() if any(s.startswith("bulb") for s in src)}
    by_probe = {li for li, src in est.sources.items() if any(s.startswith("probe") for s in src)}
    report: dict[str, Any] = {
        "num_lights": len(stage.lights),
        "num_observed": len(est.sources),
        "num_seen_as_bulbs": len(by_bulb),
        "num_seen_in_probe": len(by_probe),
        "num_in_gauge": len(gauge_lights),
        "gauge_rejected": gauge_rejected,
        "rays": len(rays),
        "rays_rejected": sum(est.rejected_rays.values()),
        "posterior_sigma_mm": {
            "mean": round(float(np.mean(list(est.sigma_mm.values()))), 3) if est.sigma_mm else None,
            "max": round(float(np.max(list(est.sigma_mm.values()))), 3) if est.sigma_mm else None,
        },
        "observed": {
            str(i): {
                "rays": len(src),
                "cameras_seeing_bulb": sorted(s.split()[1] for s in src if s.startswith("bulb")),
                "shift_from_nominal_mm": round(est.shift_mm[i], 3),
                "sigma_mm": round(est.sigma_mm[i], 3),
            }
            for i, src in est.sources.items()
        },
    }
    if found is not None:
        report["bulbs"] = {
            "candidate_light_cameras": found.candidates,
            "frames_read": found.frames_read,
            "unconfirmed_light_cameras": found.unconfirmed,
            "read_errors": found.read_errors[:20],
            "sightings": [
                {
                    "light": s.light,
                    "camera": s.camera,
                    "uv_processed": [round(s.uv[0], 3), round(s.uv[1], 3)],
                    "groups": s.groups,
                    "touching_mask": s.touching_mask,
                }
                for s in found.sightings
            ],
        }
        if found.read_errors:
            report["warnings"] = [
                f"bulbs: {len(found.read_errors)} processed frames unreadable (first: {found.read_errors[0]})"
            ]
    log(
        f"lights: {len(est.sources)}/{len(stage.lights)} observed ({len(by_bulb)} as bulbs, {len(by_probe)} "
        f"in the mirror-ball probe; {len(gauge_lights)} used in the gauge); "
        + ("the others at nominal rig positions" if len(est.sources) < len(stage.lights) else "")
    )
    report["_result"] = (reg, est.positions, gauge_lights)
    return report, probe_report
