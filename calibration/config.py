"""Settings of the calibration stage (`calibrate:` in the pipeline config, `lightstage calibrate` flags)."""

from __future__ import annotations

import hashlib
import json
from dataclasses import asdict, dataclass
from typing import Any

from lightstage.config import load, require, require_choice

METHODS = ("sfm", "nominal")


@dataclass(frozen=True)
class CalibrateConfig:
    """Settings of the calibration stage (defaults suit the simulator's `small` capture)."""

    method: str = "sfm"
    intrinsics: str | None = (
        None  # JSON from `lightstage calibrate-intrinsics` (raw-resolution K + distortion)
    )
    max_mean_reprojection_px: float = 1.0  # SfM fails above this mean reprojection error
    min_registered_fraction: float = 1.0  # SfM fails when fewer views register (1.0: every view)
    max_rig_fit_rms_mm: float = 50.0  # recovered rig vs nominal camera centres; larger = wrong stage.yaml
    max_features: int = 8192
    mask_erode_px: int = 2  # feature-mask erosion in processed pixels (scaled to the SfM images)
    sift_first_octave: int = -1  # -1: SIFT upsamples once (more, finer features; 0 halved the accuracy)
    # Match views whose nominal camera centres are within this angle seen from the object (180 or 0: every
    # pair; narrower left the demo's top camera row loose, docs/benchmarks.md), and each view with its nearest
    # few whatever the angle, so a sparse stage (few cameras, one group) keeps a connected pair graph.
    max_pair_angle_deg: float = 90.0
    min_pair_neighbours: int = 8
    # World-frame gauge: the similarity that best fits the nominal rig's camera centres AND orientations, given
    # the stage's mounting tolerances (per axis); 0 deg: centres only (Umeyama). See docs/calibration.md.
    gauge_position_sigma_mm: float = 3.0
    gauge_rotation_sigma_deg: float = 0.2
    # Lights seen directly by cameras (clipped bulbs in the processed frames) are moved onto their rays /
    # triangulated, with the nominal position as prior (per-axis sigma); the others keep nominal positions.
    observe_bulbs: bool = True
    light_prior_sigma_mm: float = 3.0  # also the lights' mounting tolerance when they join the gauge
    lights_in_gauge: bool = True  # observed lights join the camera centres/orientations in the gauge fit
    bulb_pixel_sigma: float = 0.1  # disc-centre + camera-direction uncertainty, processed pixels
    # a light further off its nominal position (in sigmas) leaves the gauge
    light_gauge_max_sigma: float = 4.0
    # A mirror-ball probe capture (capture/probe.py), when the capture has one, locates every light it mirrors.
    use_probe: bool = True
    # highlight and outline-centre uncertainty, raw pixels (5x what the simulator's frames give: real optics)
    probe_pixel_sigma: float = 0.01
    # camera rotation uncertainty after SfM (its shape error; not magnified by the mirror)
    probe_rotation_sigma_deg: float = 0.01
    probe_distance_sigma_mm: float = 0.2  # camera-to-ball distance uncertainty (cameras' relative positions)
    probe_refine_distances: bool = True  # fit each view's camera-to-ball distance together with the lights
    probe_scale: bool = True  # the ball's known radius fixes the rig's metric scale in the gauge
    probe_radius_sigma_mm: float = 0.005  # tolerance of the ball's radius
    peak_threshold: float = 0.004
    ransac_max_error_px: float = 2.0
    num_threads: int = 2
    seed: int = 0
    keep_sfm_workspace: bool = False  # keep WORK/calibration/sfm (images, database) for debugging
    show_colmap_log: bool = False  # echo COLMAP's log (always in WORK/calibration/colmap.log) to stderr

    def __post_init__(self) -> None:
        require_choice(self.method, "method", METHODS)
        for key in (
            "gauge_position_sigma_mm",
            "light_prior_sigma_mm",
            "bulb_pixel_sigma",
            "light_gauge_max_sigma",
            "probe_pixel_sigma",
        ):
            require(getattr(self, key) > 0, key, f"must be > 0, got {getattr(self, key)!r}")
        for key in (
            "probe_rotation_sigma_deg",
            "probe_distance_sigma_mm",
            "probe_radius_sigma_mm",
            "gauge_rotation_sigma_deg",
            "max_pair_angle_deg",
            "min_pair_neighbours",
        ):
            require(getattr(self, key) >= 0, key, f"must be >= 0, got {getattr(self, key)!r}")
        require(
            0.0 < self.min_registered_fraction <= 1.0,
            "min_registered_fraction",
            f"must be in (0, 1], got {self.min_registered_fraction!r}",
        )

    @classmethod
    def from_dict(cls, d: dict[str, Any] | None) -> CalibrateConfig:
        """The strict loader (`lightstage.config`): unknown keys, wrong types and bad values name the key."""
        return load(cls, d)

    def digest(self) -> str:
        """Hash of the settings that change the outputs (display-only ones left out)."""
        d = asdict(self)
        d.pop("show_colmap_log")
        return hashlib.sha256(json.dumps(d, sort_keys=True).encode()).hexdigest()[:16]
