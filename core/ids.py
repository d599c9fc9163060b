"""Identifiers every stage shares: a frame is (group, camera, light); a view is (group, camera).

Group names are the turntable yaw in degrees, three digits (`000`, `040`, ...); light indices are 0-based
(docs/conventions.md).
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True, order=True)
class FrameId:
    """One OLAT frame: (group name, camera id, 0-based light index)."""

    group: str
    camera: str
    light: int

    def __str__(self) -> str:
        return f"{self.group}/{self.camera}/{self.light:03d}"


@dataclass(frozen=True, order=True)
class ViewId:
    """One view: (group name, camera id)."""

    group: str
    camera: str

    def __str__(self) -> str:
        return f"{self.group}/{self.camera}"
