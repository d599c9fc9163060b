"""Camera, light and tonemap conventions: projection round trips and the OpenCV <-> OpenGL conversion."""

from __future__ import annotations

import numpy as np
import pytest

from lightstage.cameras import (
    PinholeCamera,
    look_at,
    opencv_to_opengl_c2w,
    opengl_c2w_to_opencv,
    pixel_centers,
    pixel_rays,
    project,
    scale_intrinsics,
)
from lightstage.lights import index_to_paper_number, light_direction, paper_number_to_index
from lightstage.tonemap import tonemap, tonemap_u8


def _camera():
    R, t = look_at(np.array([1.2, -0.4, 0.5]), np.zeros(3))
    K = np.array([[800.0, 0.0, 321.0], [0.0, 790.0, 239.5], [0.0, 0.0, 1.0]])
    return K, R, t


def test_project_then_unproject_round_trip():
    K, R, t = _camera()
    rng = np.random.default_rng(0)
    pts = rng.uniform(-0.2, 0.2, (100, 3))
    uv = project(pts, K, R, t)
    o, d = pixel_rays(uv, K, R, t)
    # each point lies on its pixel's ray
    along = np.einsum("ij,ij->i", pts - o, d)
    np.testing.assert_allclose(o + along[:, None] * d, pts, atol=1e-10)


def test_pixel_centre_convention_and_downscale():
    K, R, t = _camera()
    cam = PinholeCamera(K, R, t, 640, 480)
    small = cam.scaled(4)
    np.testing.assert_allclose(small.K[:2], K[:2] / 4)
    # the centre of low-res pixel (0, 0) is the centre of the 4x4 block of high-res pixels 0..3
    o_small, d_small = pixel_rays(np.array([0.5, 0.5]), small.K, R, t)
    o_big, d_big = pixel_rays(np.array([2.0, 2.0]), K, R, t)
    np.testing.assert_allclose(d_small, d_big, atol=1e-12)
    c = pixel_centers(3, 2)
    assert c.shape == (2, 3, 2) and tuple(c[1, 2]) == (2.5, 1.5)
    np.testing.assert_allclose(scale_intrinsics(K, 0.25)[2], [0, 0, 1])


def test_opencv_opengl_round_trip():
    K, R, t = _camera()
    c2w = opencv_to_opengl_c2w(R, t)
    R2, t2 = opengl_c2w_to_opencv(c2w)
    np.testing.assert_allclose(R2, R, atol=1e-12)
    np.testing.assert_allclose(t2, t, atol=1e-12)
    # OpenGL camera looks down -z: the world origin (looked at) is along -z_cam
    forward = -c2w[:3, 2]
    to_origin = -c2w[:3, 3] / np.linalg.norm(c2w[:3, 3])
    np.testing.assert_allclose(forward, to_origin, atol=1e-12)
    # and +y_cam (OpenGL) points up-ish in the world
    assert c2w[2, 1] > 0


def test_light_numbering_and_direction():
    assert paper_number_to_index(43) == 42
    assert index_to_paper_number(0) == 1
    np.testing.assert_array_equal(paper_number_to_index(np.array([1, 331])), [0, 330])
    d = light_direction(np.array([[0.0, 0.0, 3.0], [2.0, 0.0, 0.0]]), np.array([0.0, 0.0, 1.0]))
    np.testing.assert_allclose(d, [[0, 0, 1], [2 / np.sqrt(5), 0, -1 / np.sqrt(5)]])


@pytest.mark.parametrize("value, expected", [(0.0, 0), (1.0, 255), (5.0, 255), (0.0031308, 10)])
def test_tonemap(value, expected):
    assert tonemap_u8(np.full((1, 1, 3), value))[0, 0, 0] == expected
    assert tonemap(np.array([-1.0]))[0] == 0.0


def test_camera_rays_undo_distortion():
    """camera_rays: points along each ray project (with the camera's distortion) back to its pixel centre."""
    import cv2

    from lightstage.cameras import PinholeCamera, camera_rays, look_at, pixel_centers

    R, t = look_at(np.array([0.0, -1.0, 0.2]), np.zeros(3), np.array([0.0, 0.0, 1.0]))
    K = np.array([[60.0, 0, 16.0], [0, 60.0, 12.0], [0, 0, 1]])
    dist = np.array([-0.2, 0.05, 0.001, -0.002, 0.0])
    cam = PinholeCamera(K, R, t, 32, 24, dist)
    o, d = camera_rays(cam)
    assert o.shape == d.shape == (32 * 24, 3)
    uv, _ = cv2.projectPoints(o + 0.7 * d, cv2.Rodrigues(R)[0], t, K, dist)
    np.testing.assert_allclose(uv[:, 0], pixel_centers(32, 24).reshape(-1, 2), atol=1e-3)
