"""Renders at the paper's 2048 x 1366: `render`, `relight` and their orbits/sweeps render a band of rows at a
time (memory one image plus one band, not the whole view's rays), report progress in rays, and keep video
frames on disk rather than in memory."""

from __future__ import annotations

import numpy as np

from lightstage.cameras import PinholeCamera, camera_rays
from lightstage.training.envmap import Lights
from lightstage.training.novel_views import ImageFiles, render_bands
from lightstage.training.relight import relight_image


class RayModel:
    """A stand-in model: a ray's pixel is |direction| x light direction's first component; records batch sizes."""

    def __init__(self):
        self.batches: list[int] = []

    def render_rays(self, origins, directions, light_directions, chunk: int = 8192):
        self.batches.append(len(origins))
        return directions.abs() * light_directions[:, :1] + 0 * origins


def _camera(width: int, height: int, k1: float = 0.0) -> PinholeCamera:
    K = np.array([[1.2 * width, 0, width / 2], [0, 1.2 * width, height / 2], [0, 0, 1]])
    return PinholeCamera(K, np.eye(3), np.array([0.0, 0.0, 2.0]), width, height, np.array([k1, 0, 0, 0, 0]))


def test_render_bands_is_the_whole_image_in_bounded_batches():
    cam = _camera(2048, 1366)
    model, done = RayModel(), []
    img = render_bands(model, cam, np.array([0.5, 0.0, 0.5]), done.append, rays_per_band=65536)
    assert max(model.batches) <= 65536 and sum(done) == 2048 * 1366
    _, d = camera_rays(cam)  # the rays of the whole view at once, as before
    assert np.array_equal(img, (np.abs(d.astype(np.float32)) * np.float32(0.5)).reshape(1366, 2048, 3))


def test_relight_progress_counts_rays_within_each_light():
    cam = _camera(64, 48, k1=0.1)  # distorted: each band undoes it as camera_rays does
    lights = Lights(np.array([[1.0, 0, 0], [0.6, 0, 0.8], [0, 1.0, 0]]), np.ones((3, 3)))
    model = RayModel()
    calls = []
    from tqdm import tqdm

    original = tqdm.update

    def spy(self, n=1):
        calls.append(n)
        return original(self, n)

    tqdm.update = spy
    try:
        img = relight_image(model, cam, lights, 1.0, progress=True, batch_rays=1024)
    finally:
        tqdm.update = original
    assert sum(calls) == 3 * 64 * 48 and len(calls) >= 3 * 3  # several updates per light
    assert max(model.batches) <= 1024
    _, d = camera_rays(cam)
    ref = (np.abs(d) * 1.6).reshape(48, 64, 3)
    assert np.allclose(img, ref, rtol=1e-5)


def test_video_frames_are_read_back_from_disk(tmp_path):
    from lightstage.frames import write_image

    frames = [np.full((6, 8, 3), 40 * k, np.uint8) for k in range(3)]
    paths = []
    for k, f in enumerate(frames):
        paths.append(tmp_path / f"frame_{k:04d}.png")
        write_image(paths[-1], f)
    files = ImageFiles(paths)
    assert len(files) == 3 and all(np.array_equal(files[k], frames[k]) for k in range(3))
    assert [int(f[0, 0, 0]) for f in files] == [0, 40, 80]
