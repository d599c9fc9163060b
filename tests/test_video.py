"""Videos are H.264 MP4 (PyAV) that browsers play: a written video decodes with PyAV and reports H.264, and
the relight rotate sweep turns the envmap once, frame by frame."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from lightstage.exr_header import read_exr_header
from lightstage.frames import write_exr
from lightstage.training.envmap import pixel_directions
from lightstage.training.novel_views import write_video
from lightstage.training.relight import RelightConfig, run_relight
from lightstage.workdir import WorkDir

av = pytest.importorskip("av")


def _decode(path):
    """(codec name, pixel format, (width, height), frames as RGB arrays) of an MP4, read back with PyAV."""
    with av.open(str(path)) as container:
        stream = container.streams.video[0]
        frames = [f.to_ndarray(format="rgb24") for f in container.decode(stream)]
        ctx = stream.codec_context
        return ctx.name, ctx.format.name, (ctx.width, ctx.height), frames


def test_write_video_is_h264_that_pyav_decodes(tmp_path):
    rng = np.random.default_rng(0)
    base = rng.integers(0, 255, size=(21, 33, 3), dtype=np.uint8)  # odd sizes: padded to even
    frames = [np.roll(base, k, axis=1) for k in range(7)]
    path = write_video(tmp_path / "clip.mp4", frames, fps=12)
    codec, pix_fmt, size, decoded = _decode(path)
    assert codec == "h264" and pix_fmt == "yuv420p" and size == (34, 22)
    assert len(decoded) == 7
    # near-lossless at crf 18 (chroma subsampling of noise aside): luma-ish mean error small
    err = np.abs(decoded[3][:21, :33].astype(float).mean(-1) - frames[3].astype(float).mean(-1)).mean()
    assert err < 25, err
    assert not list(tmp_path.glob(".*.tmp*"))  # written atomically


class _LambertSphere:
    """An analytic OLAT model: a white Lambertian unit-albedo sphere at the origin (RelightableModel)."""

    centre = np.zeros(3)
    scale = 0.5

    def render_rays(self, origins, directions, light_directions, chunk=65536):
        o, d = torch.as_tensor(origins).float(), torch.as_tensor(directions).float()
        light = torch.as_tensor(light_directions).float()
        b = (o * d).sum(-1)
        disc = b * b - ((o * o).sum(-1) - 0.3**2)
        t = -b - torch.sqrt(torch.clamp(disc, min=0))
        n = (o + t[:, None] * d) / 0.3
        return (torch.clamp((n * light).sum(-1), min=0) * (disc > 0))[:, None].repeat(1, 3)

    def image_from_camera(self, camera, light_direction):
        from lightstage.cameras import pixel_centers, pixel_rays

        o, d = pixel_rays(pixel_centers(camera.width, camera.height), camera.K, camera.R, camera.t)
        light = torch.from_numpy(np.broadcast_to(np.asarray(light_direction, np.float32), d.shape).copy())
        rgb = self.render_rays(torch.from_numpy(o), torch.from_numpy(d), light)
        return rgb.numpy().reshape(camera.height, camera.width, 3)


def test_relight_rotate_sweep_writes_an_h264_turn_of_the_envmap(tmp_path):
    h, w = 8, 16
    d = pixel_directions(h, w)
    env = np.full((h, w, 3), 0.05)
    env[(d[..., 0] > 0.7) & (d[..., 2] > 0)] = 20.0  # one bright patch: the sweep carries it round
    write_exr(tmp_path / "env.exr", env.astype(np.float32), half=False)
    out = tmp_path / "relit"
    config = RelightConfig(
        envmap=str(tmp_path / "env.exr"),
        lights="8",
        cameras=["orbit:az=0,elev=10,size=24x16"],
        resolution=f"{w}x{h}",
        rotate_sweep=6,
        fps=6.0,
        out=str(out),
    )
    summary = run_relight(WorkDir.at(tmp_path / "work"), config, progress=False, model=_LambertSphere())
    sweep = summary["rotate_sweep"]
    assert sweep["frames"] == 6 and json.loads((out / "relight.json").read_text())["rotate_sweep"] == sweep
    codec, _, size, frames = _decode(sweep["video"])
    assert codec == "h264" and len(frames) == 6 and size == (24, 16)
    angles = [float(read_exr_header(out / "sweep" / f"frame_{k:04d}.exr").attributes["lightstage_rotate_deg"])
              for k in range(6)]  # fmt: skip
    assert angles == pytest.approx([0, 60, 120, 180, 240, 300])
    # the lit side of the sphere turns with the map: the frames are not all the same
    means = [f.astype(float).mean() for f in frames]
    assert max(means) - min(means) > 1.0, means
