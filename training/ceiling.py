"""The ceiling of evaluation: what a perfect prediction scores on the same test images.

For a simulated capture the simulator writes noise-free renders of every frame of the test cameras
(CAPTURE/ground_truth/clean.json, `every_light_cameras`; capture/simulate.py): object + stand radiance, no
background, bulbs, flare, noise or clipping. A perfect model predicts that render (0 outside the foreground
mask, as it is trained), and scoring it against the raw target gives the ceiling, in every metric convention
(training/metrics.py `ceiling_scores`). The render is brought into the processed frames' units as preprocess
brings the raw frames: the same area downscale to the test image's resolution, times the capture's
exposure_scale, divided by its light's relative RGB intensity (stage.yaml).

For a real capture no noise-free render exists: the ceiling is unavailable (the only perfect prediction there is
the target itself, which scores inf).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from lightstage.errors import LightstageError
from lightstage.ids import FrameId
from lightstage.workdir import WorkDir

REAL_CAPTURE = (
    "unavailable: no noise-free render of the test frames (a real capture); a perfect prediction, the target "
    "itself, scores inf"
)


class CleanRenders:
    """Noise-free renders of a simulated capture's frames, at a processed (downscaled) resolution."""

    def __init__(
        self,
        capture: Path,
        template: str,
        exposure_scale: float = 1.0,
        intensities: np.ndarray | None = None,
    ):
        self.capture, self.template, self.exposure_scale = Path(capture), template, float(exposure_scale)
        self.intensities = None if intensities is None else np.asarray(intensities, np.float64).reshape(-1, 3)

    @classmethod
    def find(cls, work: WorkDir) -> tuple[CleanRenders | None, str]:
        """(renders, note) for the capture WORK/capture.txt names; (None, "unavailable: why") without them."""
        from lightstage.capture.layout import CAPTURE_FILE, STAGE_FILE, load_capture_info
        from lightstage.capture.stage import load_stage

        try:
            truth = work.ground_truth()
        except LightstageError as e:
            return None, f"unavailable: {e}"
        capture, info = truth.capture, truth.clean_info
        if not info.is_file():
            return None, REAL_CAPTURE
        try:
            template = str(json.loads(info.read_text())["path_template"])
        except (OSError, ValueError, KeyError, TypeError) as e:
            return None, f"unavailable: {info}: unreadable ({e})"
        scale, intensities = 1.0, None
        try:
            if (capture / CAPTURE_FILE).is_file():
                scale = load_capture_info(capture / CAPTURE_FILE).exposure_scale
            if (capture / STAGE_FILE).is_file():
                intensities = load_stage(capture / STAGE_FILE).light_intensities()
        except LightstageError as e:
            return None, f"unavailable: {e}"
        return cls(
            capture, template, scale, intensities
        ), f"noise-free renders of the simulated capture ({info})"

    def path(self, frame: FrameId) -> Path:
        return self.capture / self.template.format(group=frame.group, camera=frame.camera, light=frame.light)

    def get(self, frame: FrameId | None, size: tuple[int, int]) -> np.ndarray | None:
        """(h, w, 3) float32 noise-free render of `frame` at size (w, h), or None when there is none."""
        from lightstage.frames import read_exr
        from lightstage.preprocess.downscale import downscale

        if frame is None or not self.path(frame).is_file():
            return None
        img = read_exr(self.path(frame)).astype(np.float32)
        w, h = size
        H, W = img.shape[:2]
        if W % w or H % h or W // w != H // h:
            raise LightstageError(
                f"{self.path(frame)}: {W}x{H} is not an integer multiple of the test image's {w}x{h}"
            )
        if W != w:
            img = downscale(img, float("inf"), factor=W // w).rgb
        if self.exposure_scale != 1.0:
            img *= np.float32(self.exposure_scale)
        if self.intensities is not None:  # processed frames are divided by their light's RGB intensity
            img /= self.intensities[frame.light].astype(np.float32)
        return img
