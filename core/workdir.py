"""The layout of a work directory (WORK), in one place: every stage reads and writes its files through here.

```
WORK/
  capture.txt                         # path of the raw capture this work directory processes
  manifest.json                       # capture validation manifest
  reports/<stage>.json                # per-stage record: config hash, inputs, counts, timings, errors
  preprocess/frames/<g>/<c>/<l>.exr   # 4x downscaled linear HDR, channels R G B + S (1 = saturated)
  preprocess/views/<g>/<c>/...        # mean.exr, stats.npz, wellit.png, mask.png, zones.png, overlay.png
  preprocess/probe/<pos>/<c>.json     # mirror-ball probe: ball outline + highlight per light (raw pixels)
  calibration/calibration.json        # per-view K, dist, R, t; per-(group, light) world positions; axis, yaws
  calibration/colmap/, transforms.json, layout.png
  split.json                          # train/test frames as data
  bounds.json                         # scene normalisation (centre, scale)
  shards/                             # ray shards + manifest.json; shards/test/ for evaluation images
  train/                              # checkpoints, tensorboard, previews
  eval/                               # side-by-side PNGs; metrics in reports/eval.json
```
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

from lightstage.atomic import write_text_atomic
from lightstage.errors import LightstageError
from lightstage.ids import FrameId, ViewId
from lightstage.records.ground_truth import GroundTruth

# Zone labels of the per-view zone map (used by preprocess, shards and the sampler).
ZONE_BACKGROUND = 0
ZONE_BAND = 1
ZONE_FOREGROUND = 2
DOWNSCALE = 4


@dataclass(frozen=True)
class WorkDir:
    """Paths inside a work directory."""

    root: Path

    @classmethod
    def at(cls, root: str | os.PathLike[str]) -> WorkDir:
        return cls(Path(root))

    # reports
    def report(self, stage: str) -> Path:
        return self.root / "reports" / f"{stage}.json"

    @property
    def manifest(self) -> Path:
        return self.root / "manifest.json"

    @property
    def capture_pointer(self) -> Path:
        return self.root / "capture.txt"

    def capture_path(self) -> Path:
        """The raw capture this work directory processes (WORK/capture.txt), or one clear error."""
        pointer = self.capture_pointer
        try:
            text = pointer.read_text().strip()
        except FileNotFoundError:
            raise LightstageError(
                f"{pointer}: missing (this work directory names no capture; give it: "
                f"lightstage run CAPTURE --work {self.root})"
            ) from None
        except OSError as e:
            raise LightstageError(f"{pointer}: unreadable ({e.strerror or e})") from None
        if not text:
            raise LightstageError(f"{pointer}: empty (it must hold the path of the raw capture)")
        return Path(text)

    def link_capture(self, capture: str | os.PathLike[str]) -> Path:
        """Record `capture` (made absolute) as this work directory's raw capture; atomic, unchanged if same."""
        path = Path(capture).resolve()
        if not path.is_dir():
            raise LightstageError(f"{capture}: capture directory does not exist")
        if self.root.exists() and not self.root.is_dir():
            raise LightstageError(f"{self.root}: not a directory (the work directory must be a folder)")
        current = self.capture_pointer.read_text().strip() if self.capture_pointer.is_file() else None
        if current != str(path):
            self.root.mkdir(parents=True, exist_ok=True)
            write_text_atomic(self.capture_pointer, f"{path}\n")
        return path

    def ground_truth(self) -> GroundTruth:
        """The ground truth beside the capture (simulated captures only; `.exists` says whether there is any)."""
        return GroundTruth.of(self.capture_path())

    # preprocess
    @property
    def preprocess_dir(self) -> Path:
        return self.root / "preprocess"

    def frame(self, frame: FrameId) -> Path:
        return self.preprocess_dir / "frames" / frame.group / frame.camera / f"{frame.light:03d}.exr"

    def view_dir(self, view: ViewId) -> Path:
        return self.preprocess_dir / "views" / view.group / view.camera

    def mask(self, view: ViewId) -> Path:
        return self.view_dir(view) / "mask.png"

    def zones(self, view: ViewId) -> Path:
        return self.view_dir(view) / "zones.png"

    def flare_mask(self, frame: FrameId) -> Path:
        """A frame's flare and bulb mask (preprocess/flare.py); absent when nothing of the frame is flagged."""
        return self.view_dir(ViewId(frame.group, frame.camera)) / "flare" / f"{frame.light:03d}.png"

    def wellit(self, view: ViewId) -> Path:
        return self.view_dir(view) / "wellit.png"

    def mean_image(self, view: ViewId) -> Path:
        return self.view_dir(view) / "mean.exr"

    def sfm_hdr(self, view: ViewId) -> Path:
        """Linear HDR image SfM works from (preprocess/sfm_image.py), at raw / sfm factor."""
        return self.view_dir(view) / "sfm.exr"

    def sfm_image(self, view: ViewId) -> Path:
        """8-bit tonemapped SfM image (one exposure for the capture)."""
        return self.view_dir(view) / "sfm.png"

    def sfm_mask(self, view: ViewId) -> Path:
        """The view's mask at the SfM image's resolution (SfM features only on the object)."""
        return self.view_dir(view) / "sfm_mask.png"

    @property
    def probe_dir(self) -> Path:
        """Per-view measurements of the capture's mirror-ball probe (preprocess/probe.py)."""
        return self.preprocess_dir / "probe"

    def probe_view(self, position: str, camera: str) -> Path:
        return self.probe_dir / position / f"{camera}.json"

    @property
    def sfm_info(self) -> Path:
        """JSON: the SfM images' downscale factor from raw, size, lights and exposure."""
        return self.preprocess_dir / "sfm_images.json"

    # calibration
    @property
    def calibration_dir(self) -> Path:
        return self.root / "calibration"

    @property
    def calibration(self) -> Path:
        return self.calibration_dir / "calibration.json"

    # split, bounds, shards
    @property
    def split(self) -> Path:
        return self.root / "split.json"

    @property
    def bounds(self) -> Path:
        return self.root / "bounds.json"

    @property
    def shards_dir(self) -> Path:
        return self.root / "shards"

    # training and evaluation
    @property
    def train_dir(self) -> Path:
        return self.root / "train"

    @property
    def eval_dir(self) -> Path:
        return self.root / "eval"
