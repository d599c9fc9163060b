"""The viewer's display resolution and byte budget. A paper-resolution view (2048 x 1366) holds 16.8 MB per half-float
basis component, so a ring of 27 views at full resolution would be gigabytes; the viewer downscales every view to
a display size (area average, the camera's intrinsics scaled with it) and shares a byte budget out over the views,
capping each view's component count so that the whole bundle stays within it (docs/viewer.md)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from lightstage.cameras import PinholeCamera
from lightstage.errors import LightstageError

COMPONENT_BYTES_PER_PIXEL = 6  # RGB float16
FLOAT_JSON_BYTES = 26  # the longest float a manifest writes ("-1.2345678901234567e-123", a comma, a space)


def display_size(width: int, height: int, longest: int) -> tuple[int, int]:
    """(w, h) of a view shown with its longest side at most `longest` pixels (0: as processed); never enlarged."""
    if longest < 0:
        raise LightstageError(f"--display-size must be >= 0, got {longest}")
    if longest == 0 or max(width, height) <= longest:
        return int(width), int(height)
    scale = longest / max(width, height)
    return max(1, round(width * scale)), max(1, round(height * scale))


def display_camera(camera: PinholeCamera, longest: int) -> PinholeCamera:
    """The camera whose pixels are the display-size image of `camera`'s (fx, cx by the width ratio, fy, cy by the
    height ratio: an area resize maps pixel edges linearly, so pixel centres stay at (i + 0.5) / scale)."""
    w, h = display_size(camera.width, camera.height, longest)
    if (w, h) == (camera.width, camera.height):
        return camera
    K = np.array(camera.K, np.float64, copy=True)
    K[0, :] *= w / camera.width
    K[1, :] *= h / camera.height
    return PinholeCamera(K, camera.R, camera.t, w, h, camera.dist)


def downscale(image: np.ndarray, width: int, height: int) -> np.ndarray:
    """(height, width, C) float32 area average of `image` (itself when the size already matches)."""
    import cv2

    img = np.asarray(image, np.float32)
    if img.shape[:2] == (height, width):
        return img
    return cv2.resize(img, (width, height), interpolation=cv2.INTER_AREA).reshape(height, width, -1)


@dataclass
class Budget:
    """Bytes for basis components shared out view by view: each view may use an equal share of what is left, so
    views that need less (cropped model renders, low-rank bases) leave more to the later ones, and the total
    never exceeds the start."""

    remaining: int
    views_left: int

    def share(self) -> int:
        """Bytes the next view may use."""
        return self.remaining // max(1, self.views_left)

    def spend(self, nbytes: int) -> None:
        self.remaining -= int(nbytes)
        self.views_left -= 1


def component_cap(share: int, width: int, height: int, what: str) -> int:
    """Most components of a width x height view within `share` bytes; an error when not even one fits."""
    per = width * height * COMPONENT_BYTES_PER_PIXEL
    if share < per:
        raise LightstageError(
            f"{what}: one {width}x{height} basis component is {per / 1e6:.1f} MB but the bundle budget leaves "
            f"{share / 1e6:.1f} MB per view; lower --display-size or raise --bundle-mb"
        )
    return share // per


def reserved_bytes(
    static_bytes: int,
    view_lights: Sequence[int],
    basis_lights: Sequence[int],
    envmaps: int,
    envmap_pixels: int,
    max_components: int,
    rotation_steps: int = 360,
) -> int:
    """An upper bound of everything in a bundle but the components: the page, the manifest (coefficients of each
    view, each basis's directions, triangles, rim and light indices), and per envmap its radiance, preview and
    one (rotation_steps, L, 3) float32 weight table per basis."""
    manifest = 20_000 + sum(2_000 + max_components * L * FLOAT_JSON_BYTES for L in view_lights)
    manifest += sum(1_000 + L * (3 * FLOAT_JSON_BYTES + 2 * 3 * 8 + 2 * 2 * 8 + 8) for L in basis_lights)
    manifest += envmaps * (1_000 + len(basis_lights) * 100 + 2 * FLOAT_JSON_BYTES)
    per_envmap = envmap_pixels * 12 + 256 * 128 * 4 + 1_000 + rotation_steps * 12 * sum(basis_lights)
    return static_bytes + manifest + envmaps * per_envmap
