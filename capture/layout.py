"""The raw-capture contract: a directory with `stage.yaml`, `capture.yaml` and the frames.

`capture.yaml` maps every frame identifier (group, camera, light) to a file through a path template
(default `frames/{group}/{camera}/{light:03d}.exr`) and carries optional exposure metadata.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from lightstage.atomic import write_text_atomic
from lightstage.capture.stage import Stage, load_stage
from lightstage.config import ConfigError, load, read_yaml, require
from lightstage.errors import LightstageError
from lightstage.ids import FrameId, ViewId

DEFAULT_PATH_TEMPLATE = "frames/{group}/{camera}/{light:03d}.exr"
STAGE_FILE = "stage.yaml"
CAPTURE_FILE = "capture.yaml"


@dataclass(frozen=True)
class CaptureInfo:
    """Contents of capture.yaml."""

    path_template: str = DEFAULT_PATH_TEMPLATE
    exposure_scale: float = 1.0  # multiply raw pixels by this to get the stage's radiometric units
    object_name: str = ""
    notes: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        try:
            self.path_template.format(group="000", camera="cam00", light=0)
        except (KeyError, IndexError, ValueError) as e:
            raise ConfigError(
                f"{self.path_template!r} must use only {{group}}, {{camera}} and {{light}} ({e})",
                "path_template",
            ) from None
        require(
            self.exposure_scale > 0,
            "exposure_scale",
            f"expected a positive number, got {self.exposure_scale!r}",
        )

    def to_dict(self) -> dict[str, Any]:
        return {
            "path_template": self.path_template,
            "exposure_scale": float(self.exposure_scale),
            "object_name": self.object_name,
            "notes": dict(self.notes),
        }


# user-supplied masks: <capture>/masks/<group>/<camera>.png (optional, per view)
USER_MASKS = "masks"


@dataclass(frozen=True)
class Capture:
    """A raw capture on disk: where it is, its stage and its capture.yaml."""

    root: Path
    stage: Stage
    info: CaptureInfo

    def frame_path(self, frame: FrameId) -> Path:
        return self.root / self.info.path_template.format(
            group=frame.group, camera=frame.camera, light=frame.light
        )

    def user_mask(self, view: ViewId) -> Path:
        """Where the lab's own foreground mask of a view lies, if it has one: masks/<group>/<camera>.png at the
        raw resolution (docs/capture-format.md); preprocess uses it as it is."""
        return self.root / USER_MASKS / view.group / f"{view.camera}.png"

    def frames(self) -> Iterator[FrameId]:
        """Every expected frame, ordered group -> camera -> light."""
        for g in self.stage.groups:
            for c in self.stage.cameras:
                for lt in self.stage.lights:
                    yield FrameId(g.name, c.id, lt.index)

    def views(self) -> Iterator[ViewId]:
        for g in self.stage.groups:
            for c in self.stage.cameras:
                yield ViewId(g.name, c.id)


def load_capture_info(path: str | os.PathLike[str]) -> CaptureInfo:
    """Read and validate capture.yaml."""
    path = Path(path)
    data = read_yaml(path, "capture description") or {}
    if not isinstance(data, dict):
        raise LightstageError(f"{path}: expected a mapping at the top level")
    return load(CaptureInfo, data, str(path))


def save_capture_info(info: CaptureInfo, path: str | os.PathLike[str]) -> None:
    write_text_atomic(path, yaml.safe_dump(info.to_dict(), sort_keys=False))


def open_capture(root: str | os.PathLike[str]) -> Capture:
    """Open a capture directory: reads and validates stage.yaml and capture.yaml (not the frames)."""
    root = Path(root)
    if not root.is_dir():
        raise LightstageError(f"{root}: capture directory does not exist")
    for name in (STAGE_FILE, CAPTURE_FILE):
        if not (root / name).is_file():
            raise LightstageError(
                f"{root}: missing {name} (a capture holds stage.yaml, capture.yaml and frames/)"
            )
    return Capture(root, load_stage(root / STAGE_FILE), load_capture_info(root / CAPTURE_FILE))
