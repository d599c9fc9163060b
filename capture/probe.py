"""The mirror-ball light-probe contract: `CAPTURE/probe/probe.yaml` says where the probe frames are and what the
ball is (optional; a capture without a probe has no `probe/` folder).

A lab locates its lights by photographing a chrome ball with every camera under each light alone, at a few
placements of the ball (`positions`; the simulator names them after the turntable group they were shot in), plus
one `ambient` frame per (position, camera) with the room light on so the ball's silhouette is visible. Light
indices are the stage's (0..N-1, as in stage.yaml); frames are linear HDR EXRs at the stage's raw resolution.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from lightstage.atomic import write_text_atomic
from lightstage.config import check_keys, read_yaml
from lightstage.errors import LightstageError

PROBE_FILE = "probe/probe.yaml"
PROBE_FORMAT_VERSION = 1
DEFAULT_PROBE_TEMPLATE = "probe/{position}/{camera}/{light:03d}.exr"
DEFAULT_AMBIENT_TEMPLATE = "probe/{position}/{camera}/ambient.exr"


@dataclass(frozen=True)
class ProbeInfo:
    """A mirror-ball probe capture: where its frames are and what the ball is."""

    radius_m: float  # chrome ball radius (metres), known from its spec
    positions: tuple[str, ...]  # folder names, one per placement of the ball (simulator: the group names)
    path_template: str = DEFAULT_PROBE_TEMPLATE  # OLAT frames, relative to the capture root
    ambient_template: str = DEFAULT_AMBIENT_TEMPLATE  # room-light frame (ball silhouette)
    notes: dict = field(default_factory=dict)

    def frame(self, root: Path, position: str, camera: str, light: int) -> Path:
        """Path of the OLAT frame of `light` seen by `camera` with the ball at `position`."""
        return Path(root) / self.path_template.format(position=position, camera=camera, light=light)

    def ambient(self, root: Path, position: str, camera: str) -> Path:
        """Path of the room-light (silhouette) frame of `camera` with the ball at `position`."""
        return Path(root) / self.ambient_template.format(position=position, camera=camera)

    def to_dict(self) -> dict[str, Any]:
        return {
            "format_version": PROBE_FORMAT_VERSION,
            "radius_m": float(self.radius_m),
            "positions": list(self.positions),
            "path_template": self.path_template,
            "ambient_template": self.ambient_template,
            "notes": dict(self.notes),
        }


def _check_template(path: Path, key: str, template: Any, needs_light: bool) -> str:
    if not isinstance(template, str) or not template:
        raise LightstageError(f"{path}: {key}: expected a non-empty string, got {template!r}")
    fields = "{position}, {camera} and {light}" if needs_light else "{position} and {camera}"
    try:
        a = template.format(position="p0", camera="c0", light=0)
        b = template.format(position="p1", camera="c1", light=1)
    except (KeyError, IndexError, ValueError, AttributeError) as e:
        raise LightstageError(f"{path}: {key}: {template!r} must use only {fields} ({e})") from None
    if "{position" not in template or "{camera" not in template or a == b:
        raise LightstageError(f"{path}: {key}: {template!r} must use {fields}")
    if needs_light and template.format(position="p0", camera="c0", light=1) == a:
        raise LightstageError(f"{path}: {key}: {template!r} must use {{light}}")
    if os.path.isabs(a) or ".." in Path(a).parts:
        raise LightstageError(f"{path}: {key}: {template!r} must be relative to the capture root")
    return template


PROBE_KEYS = ("format_version", "radius_m", "positions", "path_template", "ambient_template", "notes")


def probe_info_from_dict(data: Any, path: Path) -> ProbeInfo:
    """Validate a probe.yaml mapping; errors name `path` and the field."""
    if not isinstance(data, dict):
        raise LightstageError(f"{path}: expected a mapping at the top level")
    check_keys(data, PROBE_KEYS, (), str(path))
    version = data.get("format_version", PROBE_FORMAT_VERSION)
    if version != PROBE_FORMAT_VERSION:
        raise LightstageError(f"{path}: format_version: expected {PROBE_FORMAT_VERSION}, got {version!r}")
    radius = data.get("radius_m")
    if (
        not isinstance(radius, int | float)
        or isinstance(radius, bool)
        or not math.isfinite(radius)
        or not radius > 0
    ):
        raise LightstageError(f"{path}: radius_m: expected a positive number of metres, got {radius!r}")
    positions = data.get("positions")
    if not isinstance(positions, list | tuple) or not positions:
        raise LightstageError(
            f"{path}: positions: expected a non-empty list of folder names, got {positions!r}"
        )
    for i, name in enumerate(positions):
        if not isinstance(name, str) or not name or "/" in name or "\\" in name or name in (".", ".."):
            raise LightstageError(
                f"{path}: positions[{i}]: expected a folder name (a quoted string such as '000'), got {name!r}"
            )
    if len(set(positions)) != len(positions):
        raise LightstageError(f"{path}: positions: duplicate names in {positions!r}")
    template = _check_template(path, "path_template", data.get("path_template", DEFAULT_PROBE_TEMPLATE), True)
    ambient = _check_template(
        path, "ambient_template", data.get("ambient_template", DEFAULT_AMBIENT_TEMPLATE), False
    )
    if ambient.format(position="p0", camera="c0") in {
        template.format(position="p0", camera="c0", light=k) for k in range(1000)
    }:
        raise LightstageError(
            f"{path}: ambient_template: {ambient!r} collides with path_template {template!r}"
        )
    notes = data.get("notes", {}) or {}
    if not isinstance(notes, dict):
        raise LightstageError(f"{path}: notes: expected a mapping")
    return ProbeInfo(float(radius), tuple(positions), template, ambient, notes)


def load_probe_info(capture_root: str | os.PathLike[str]) -> ProbeInfo | None:
    """Read and validate CAPTURE/probe/probe.yaml; None when the capture has no probe."""
    path = Path(capture_root) / PROBE_FILE
    if not path.exists():
        return None
    return probe_info_from_dict(read_yaml(path, "probe description"), path)


def save_probe_info(info: ProbeInfo, capture_root: str | os.PathLike[str]) -> Path:
    """Validate `info` and write it to CAPTURE/probe/probe.yaml atomically; returns the path."""
    path = Path(capture_root) / PROBE_FILE
    data = info.to_dict()
    probe_info_from_dict(data, path)  # never write a file that would not load
    write_text_atomic(path, yaml.safe_dump(data, sort_keys=False))
    return path


__all__ = [
    "PROBE_FILE",
    "DEFAULT_PROBE_TEMPLATE",
    "DEFAULT_AMBIENT_TEMPLATE",
    "ProbeInfo",
    "load_probe_info",
    "save_probe_info",
    "probe_info_from_dict",
]
