"""The ground truth a simulated capture carries beside its frames (CAPTURE/ground_truth/), in one place.

The simulator writes it; preprocess (mask IoU), calibration (pose and light errors), training (the noise-free
ceiling) and the demo report read it. A real capture has no `ground_truth/` folder and every reader says so.

```
CAPTURE/ground_truth/
  geometry.json                  # true cameras, lights, axis, yaws (a Calibration, method "ground_truth")
  scene.json                     # the simulator's scene (SimScene)
  nuisances.json                 # what the realism layer put in: bulbs in view, flares, LED gains
  probe.json                     # the mirror-ball probe's true ball and highlights
  clean.json                     # noise-free renders: path_template, lights, every_light_cameras
  clean/<g>/<c>/<lll>.exr        # noise-free renders of some frames (raw resolution)
  masks/<g>/<c>.png              # true foreground masks (raw resolution)
```
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

from lightstage.ids import ViewId

FOLDER = "ground_truth"
CLEAN_TEMPLATE = "ground_truth/clean/{group}/{camera}/{light:03d}.exr"  # relative to the capture root


@dataclass(frozen=True)
class GroundTruth:
    """Paths of a simulated capture's ground truth; `exists` is False for a real capture."""

    capture: Path

    @classmethod
    def of(cls, capture_root: str | os.PathLike[str]) -> GroundTruth:
        return cls(Path(capture_root))

    @property
    def root(self) -> Path:
        return self.capture / FOLDER

    @property
    def exists(self) -> bool:
        return self.root.is_dir()

    @property
    def geometry(self) -> Path:
        return self.root / "geometry.json"

    @property
    def scene(self) -> Path:
        return self.root / "scene.json"

    @property
    def nuisances(self) -> Path:
        return self.root / "nuisances.json"

    @property
    def probe(self) -> Path:
        return self.root / "probe.json"

    @property
    def clean_info(self) -> Path:
        return self.root / "clean.json"

    @property
    def masks_dir(self) -> Path:
        return self.root / "masks"

    def mask(self, view: ViewId) -> Path:
        return self.masks_dir / view.group / f"{view.camera}.png"
