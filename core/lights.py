"""Light conventions, in one place.

Lights are white point lights with positions in metres, locked to the camera rig. Indices are 0-based in
code and files; the paper numbers them from 1 (`paper_number_to_index` is the only mapping). The light
direction of the paper is omega = normalize(p_light - scene_centre).
"""

from __future__ import annotations

import numpy as np


def paper_number_to_index(number: int | np.ndarray) -> int | np.ndarray:
    """Paper's 1-based light/camera number to our 0-based index."""
    return np.asarray(number) - 1 if isinstance(number, np.ndarray) else int(number) - 1


def index_to_paper_number(index: int | np.ndarray) -> int | np.ndarray:
    """Our 0-based index to the paper's 1-based number."""
    return np.asarray(index) + 1 if isinstance(index, np.ndarray) else int(index) + 1


def light_direction(position: np.ndarray, scene_centre: np.ndarray | None = None) -> np.ndarray:
    """Unit direction(s) from the scene centre towards the light position(s), shape (..., 3)."""
    p = np.asarray(position, dtype=np.float64)
    c = np.zeros(3) if scene_centre is None else np.asarray(scene_centre, dtype=np.float64)
    d = p - c
    return d / np.linalg.norm(d, axis=-1, keepdims=True)
