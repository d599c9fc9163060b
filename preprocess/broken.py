"""The frame-level drop for broken frames: a light that misfired or a frame taken at the wrong exposure.

The rig turns the cameras and lights together, so a camera sees a light from the same place in every group; only
the object turns. A frame's mean level (flare.frame_levels) is therefore compared with the same camera and light in
the other groups: a frame more than `limit` stops from their median is broken, where the limit is `sigmas` x the
capture's own robust spread of those differences (1.4826 x their median absolute value), and at least
`min_stops`. A misfired light leaves the frame at the dark level, many stops down; a wrong exposure scales the whole
frame. Needs at least 3 groups (with fewer, nothing is dropped). Frames whose light is in view are not tested
(whether the turning object hides the bulb changes their level from group to group); levels leave out blocks with
a saturated pixel. Everything else, flares and bulbs in view included, stays in the split (docs/preprocess.md).
"""

from __future__ import annotations

import numpy as np

from lightstage.ids import FrameId, ViewId

MIN_GROUPS = 3
TINY = 1e-12  # levels at or below this count as this (log of a black frame)


def broken_frames(
    levels: dict[ViewId, dict[int, float]], sigmas: float, min_stops: float
) -> dict[FrameId, str]:
    """Broken frames -> the reason (one line): frames whose level departs from the median of the same camera and
    light over the groups by more than the limit (module docstring)."""
    by_pair: dict[tuple[str, int], list[tuple[str, float]]] = {}
    for view, per_light in levels.items():
        for light, level in per_light.items():
            by_pair.setdefault((view.camera, int(light)), []).append((view.group, float(level)))
    devs: dict[FrameId, float] = {}
    for (camera, light), items in by_pair.items():
        if len(items) < MIN_GROUPS:
            continue
        stops = np.log2(np.maximum([lv for _, lv in items], TINY))
        centre = float(np.median(stops))
        for (group, _), s in zip(items, stops, strict=True):
            devs[FrameId(group, camera, light)] = float(s - centre)
    if not devs:
        return {}
    spread = 1.4826 * float(np.median(np.abs(list(devs.values()))))
    limit = max(min_stops, sigmas * spread)
    return {
        frame: (
            f"frame level {d:+.1f} stops from the median of camera {frame.camera}, light {frame.light} in the "
            f"other groups (limit {limit:.2f} stops): the light misfired or the exposure is wrong"
        )
        for frame, d in sorted(devs.items(), key=lambda kv: str(kv[0]))
        if abs(d) > limit
    }
