"""Camera conventions, in one place.

OpenCV pinhole: x right, y down, z forward; world-to-camera x_c = R x_w + t. Pixel (i, j) (column, row)
has its centre at (i + 0.5, j + 0.5), so an integer downscale by s divides fx, fy, cx, cy by exactly s.
OpenGL / nerfstudio / Blender cameras look down -z with +y up: the conversion flips the y and z axes.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

# Camera-axis flip between OpenCV (x right, y down, z forward) and OpenGL (x right, y up, z backward).
OPENCV_TO_OPENGL = np.diag([1.0, -1.0, -1.0])


@dataclass(frozen=True)
class PinholeCamera:
    """Intrinsics and world-to-camera pose of one view, OpenCV convention, units of metres and pixels."""

    K: np.ndarray  # 3x3
    R: np.ndarray  # 3x3 world-to-camera rotation
    t: np.ndarray  # 3 world-to-camera translation
    width: int
    height: int
    dist: np.ndarray = field(default_factory=lambda: np.zeros(5))  # k1 k2 p1 p2 k3

    @property
    def center(self) -> np.ndarray:
        """Camera centre in world coordinates."""
        return camera_center(self.R, self.t)

    def scaled(self, factor: int) -> PinholeCamera:
        """The same camera at 1/factor resolution (exact under the pixel-centre convention)."""
        if self.width % factor or self.height % factor:
            raise ValueError(f"resolution {self.width}x{self.height} is not divisible by {factor}")
        return PinholeCamera(
            scale_intrinsics(self.K, 1.0 / factor),
            self.R,
            self.t,
            self.width // factor,
            self.height // factor,
            self.dist,
        )


def scale_intrinsics(K: np.ndarray, scale: float) -> np.ndarray:
    """Intrinsics after resizing the image by `scale` (0.25 for a 4x downscale): fx, fy, cx, cy all scale."""
    K2 = np.array(K, dtype=np.float64, copy=True)
    K2[:2, :] *= scale
    K2[2, :] = [0.0, 0.0, 1.0]
    return K2


def camera_center(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """World position of the camera centre: C = -R^T t."""
    return -np.asarray(R).T @ np.asarray(t)


def world_to_camera(points: np.ndarray, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Transform (..., 3) world points into the camera frame."""
    return points @ np.asarray(R).T + np.asarray(t)


def project(points: np.ndarray, K: np.ndarray, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Project (..., 3) world points to continuous pixel coordinates (..., 2) (no distortion)."""
    uvw = world_to_camera(points, R, t) @ np.asarray(K).T
    return uvw[..., :2] / uvw[..., 2:3]


def pixel_centers(width: int, height: int) -> np.ndarray:
    """(height, width, 2) continuous coordinates of pixel centres, (i + 0.5, j + 0.5)."""
    i, j = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
    return np.stack([i, j], axis=-1)


def pixel_rays(uv: np.ndarray, K: np.ndarray, R: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World-space rays through continuous pixel coordinates uv (..., 2): (origins, unit directions)."""
    uv = np.asarray(uv, dtype=np.float64)
    uv1 = np.concatenate([uv, np.ones_like(uv[..., :1])], axis=-1)
    d_cam = uv1 @ np.linalg.inv(K).T
    d_world = d_cam @ np.asarray(R)  # R^T d for row vectors
    d_world /= np.linalg.norm(d_world, axis=-1, keepdims=True)
    origins = np.broadcast_to(camera_center(R, t), d_world.shape).copy()
    return origins, d_world


def undistort_pixels(uv: np.ndarray, K: np.ndarray, dist: np.ndarray) -> np.ndarray:
    """Continuous pixel coordinates (N, 2) of a distorted OpenCV camera -> where the ideal pinhole camera K sees
    the same rays (unchanged when all distortion coefficients are zero)."""
    uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    if not np.any(np.asarray(dist) != 0):
        return uv
    import cv2

    return cv2.undistortPoints(uv[:, None, :], K, np.asarray(dist, np.float64), P=K)[:, 0]


def camera_rays(camera: PinholeCamera) -> tuple[np.ndarray, np.ndarray]:
    """World rays (H*W, 3) through every pixel centre of `camera` in raster order, distortion undone."""
    uv = undistort_pixels(pixel_centers(camera.width, camera.height), camera.K, camera.dist)
    return pixel_rays(uv, camera.K, camera.R, camera.t)


def opencv_to_opengl_c2w(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """4x4 camera-to-world matrix in the OpenGL/nerfstudio convention from an OpenCV world-to-camera pose."""
    c2w = np.eye(4)
    c2w[:3, :3] = np.asarray(R).T @ OPENCV_TO_OPENGL
    c2w[:3, 3] = camera_center(R, t)
    return c2w


def opengl_c2w_to_opencv(c2w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Inverse of `opencv_to_opengl_c2w`: (R, t) world-to-camera in the OpenCV convention."""
    c2w = np.asarray(c2w, dtype=np.float64)
    R = (c2w[:3, :3] @ OPENCV_TO_OPENGL).T
    t = -R @ c2w[:3, 3]
    return R, t


def look_at(
    center: np.ndarray, target: np.ndarray, up: np.ndarray = (0.0, 0.0, 1.0)
) -> tuple[np.ndarray, np.ndarray]:
    """OpenCV world-to-camera (R, t) for a camera at `center` looking at `target` with world `up` roughly up."""
    center = np.asarray(center, dtype=np.float64)
    z = np.asarray(target, dtype=np.float64) - center
    z /= np.linalg.norm(z)
    up = np.asarray(up, dtype=np.float64)
    if abs(np.dot(z, up)) > 0.999:  # looking straight up or down: pick another up
        up = np.array([0.0, 1.0, 0.0])
    x = np.cross(z, up)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])
    return R, -R @ center


def rotation_z(angle_rad: float) -> np.ndarray:
    """Right-handed rotation about +z (the nominal turntable axis)."""
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def rotation_axis_angle(axis: np.ndarray, angle_rad: float) -> np.ndarray:
    """Rodrigues rotation about a unit `axis` by `angle_rad` (right-handed)."""
    axis = np.asarray(axis, dtype=np.float64)
    axis = axis / np.linalg.norm(axis)
    kx = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle_rad) * kx + (1 - np.cos(angle_rad)) * kx @ kx
