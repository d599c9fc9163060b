"""The calibration record (`WORK/calibration/calibration.json`): what every later stage needs of the geometry.

Per view (group, camera): K at raw and processed resolution, distortion, world-to-camera R and t (OpenCV,
world frame of the conventions). Per (group, light): world position. Plus the turntable axis and yaws.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from lightstage.atomic import write_json_atomic
from lightstage.cameras import PinholeCamera, scale_intrinsics
from lightstage.errors import LightstageError
from lightstage.ids import ViewId
from lightstage.rig import TurntableAxis
from lightstage.workdir import DOWNSCALE

CALIBRATION_FORMAT_VERSION = 1


@dataclass(frozen=True)
class ViewCalibration:
    """One calibrated view at raw resolution (processed = raw / DOWNSCALE)."""

    K_raw: np.ndarray
    R: np.ndarray
    t: np.ndarray
    width_raw: int
    height_raw: int
    dist: np.ndarray = field(default_factory=lambda: np.zeros(5))

    def camera(self, downscale: int = DOWNSCALE) -> PinholeCamera:
        """The view's camera at raw (downscale=1) or processed (default) resolution."""
        return PinholeCamera(self.K_raw, self.R, self.t, self.width_raw, self.height_raw, self.dist).scaled(
            downscale
        )


@dataclass(frozen=True)
class Calibration:
    """Cameras and lights of a whole capture in the world frame."""

    method: str  # "sfm" | "nominal" | "ground_truth"
    views: dict[ViewId, ViewCalibration]
    light_positions: dict[str, np.ndarray]  # group -> (L, 3) world positions
    axis: TurntableAxis
    yaws_deg: dict[str, float]
    scene_centre: np.ndarray = field(default_factory=lambda: np.zeros(3))

    def light_directions(self, group: str) -> np.ndarray:
        """(L, 3) unit directions omega = normalize(p - scene_centre) for a group."""
        from lightstage.lights import light_direction

        return light_direction(self.light_positions[group], self.scene_centre)

    def to_dict(self) -> dict[str, Any]:
        return {
            "format_version": CALIBRATION_FORMAT_VERSION,
            "method": self.method,
            "downscale": DOWNSCALE,
            "scene_centre": np.asarray(self.scene_centre, float).tolist(),
            "turntable_axis": {
                "direction": list(map(float, self.axis.direction)),
                "point": list(map(float, self.axis.point)),
            },
            "yaws_deg": {g: float(y) for g, y in self.yaws_deg.items()},
            "views": {
                str(v): {
                    "group": v.group,
                    "camera": v.camera,
                    "width_raw": c.width_raw,
                    "height_raw": c.height_raw,
                    "K_raw": np.asarray(c.K_raw, float).tolist(),
                    "K": scale_intrinsics(c.K_raw, 1.0 / DOWNSCALE).tolist(),
                    "dist": np.asarray(c.dist, float).tolist(),
                    "R": np.asarray(c.R, float).tolist(),
                    "t": np.asarray(c.t, float).tolist(),
                }
                for v, c in sorted(self.views.items())
            },
            "light_positions": {g: np.asarray(p, float).tolist() for g, p in self.light_positions.items()},
        }

    def save(self, path: str | os.PathLike[str]) -> None:
        write_json_atomic(path, self.to_dict())

    @classmethod
    def load(cls, path: str | os.PathLike[str]) -> Calibration:
        path = Path(path)
        try:
            d = json.loads(path.read_text())
            if d.get("format_version") != CALIBRATION_FORMAT_VERSION:
                raise LightstageError(f"{path}: unsupported calibration format {d.get('format_version')!r}")
            views = {
                ViewId(v["group"], v["camera"]): ViewCalibration(
                    np.array(v["K_raw"]),
                    np.array(v["R"]),
                    np.array(v["t"]),
                    int(v["width_raw"]),
                    int(v["height_raw"]),
                    np.array(v["dist"]),
                )
                for v in d["views"].values()
            }
            return cls(
                method=d["method"],
                views=views,
                light_positions={g: np.array(p) for g, p in d["light_positions"].items()},
                axis=TurntableAxis(
                    tuple(d["turntable_axis"]["direction"]), tuple(d["turntable_axis"]["point"])
                ),
                yaws_deg={g: float(y) for g, y in d["yaws_deg"].items()},
                scene_centre=np.array(d.get("scene_centre", [0.0, 0.0, 0.0])),
            )
        except OSError as e:
            raise LightstageError(
                f"{path}: cannot read calibration ({e.strerror}); run `lightstage calibrate`"
            ) from None
        except (KeyError, TypeError, ValueError) as e:
            raise LightstageError(f"{path}: malformed calibration ({type(e).__name__}: {e})") from None
