"""The viewer at paper resolution: the display size (views area-downscaled, cameras scaled with them) and the
byte budget that bounds a bundle (docs/viewer.md), checked on the sizes of a paper work directory and on a
small generated capture built for real."""

from __future__ import annotations

import json

import numpy as np
import pytest

from lightstage.cameras import PinholeCamera, project
from lightstage.errors import LightstageError
from lightstage.viewer.build import ViewerConfig, build_viewer
from lightstage.viewer.display import (
    COMPONENT_BYTES_PER_PIXEL,
    Budget,
    component_cap,
    display_camera,
    display_size,
    downscale,
    reserved_bytes,
)

PAPER = (2048, 1366)


def test_paper_work_directory_default_bundle_is_within_300_mb():
    """The default ring of a paper work directory (9 groups: 9 captured views of 331 lights; 9 + 9 novel model
    views of 64 lights), each view using all its share: at most 300 MB, and at least 9 components a view (cropped model views take less in practice)."""
    config = ViewerConfig()
    w, h = display_size(*PAPER, config.display_size)
    assert (w, h) == (512, 342)
    views = [331] * 9 + [config.basis_lights] * 18
    bases = [331] * 9 + [config.basis_lights]
    reserve = reserved_bytes(20_000, views, bases, 1, 32 * 16, config.max_components)
    budget = Budget(int(config.bundle_mb * 1e6) - reserve, len(views))
    caps = []
    for _ in views:
        caps.append(min(config.max_components, component_cap(budget.share(), w, h, "view")))
        budget.spend(caps[-1] * w * h * COMPONENT_BYTES_PER_PIXEL)
    assert budget.remaining >= 0 and reserve + sum(caps) * w * h * 6 <= 300e6
    assert min(caps) >= 9, caps
    # at the processed resolution not one component of a view fits its share: an error naming the options
    with pytest.raises(LightstageError, match="--display-size"):
        component_cap(Budget(int(300e6) - reserve, len(views)).share(), *PAPER, "view 000/cam00")


def test_display_camera_and_downscale_agree():
    """The display camera projects a point where the downscaled image shows it (area average, pixel centres
    at i + 0.5), and small views are never enlarged."""
    K = np.array([[2400.0, 0, 1024.0], [0, 2400.0, 683.0], [0, 0, 1]])
    cam = PinholeCamera(K, np.eye(3), np.array([0.0, 0.0, 2.0]), *PAPER)
    small = display_camera(cam, 512)
    assert (small.width, small.height) == (512, 342)
    point = np.array([[0.05, -0.03, 0.1]])
    uv, uv_small = project(point, cam.K, cam.R, cam.t)[0], project(point, small.K, small.R, small.t)[0]
    assert np.allclose(uv_small, uv * [512 / 2048, 342 / 1366])
    assert display_camera(cam, 0) is cam and display_size(48, 32, 512) == (48, 32)
    img = np.zeros((1366, 2048, 3), np.float32)
    img[683:, :] = 1.0  # the lower half lit
    out = downscale(img, 512, 342)
    assert out.shape == (342, 512, 3) and out.dtype == np.float32
    assert abs(out.mean() - img.mean()) < 2e-3


def test_build_at_a_display_size_within_a_byte_budget(tmp_path):
    """A generated capture built at half its size within a tight budget: the views are downscaled, the bundle
    stays within --bundle-mb, the capped views report the error they show, and the compressed basis
    reproduces the downscaled frames to that error."""
    from support.fixtures import make_synthetic_work
    from test_viewer import shade_frames

    from lightstage.ids import FrameId
    from lightstage.records.processed import read_processed

    work, _ = make_synthetic_work(tmp_path, num_cameras=2, num_lights=12, num_groups=2, width=96, height=64)
    shade_frames(work)
    full = build_viewer(
        work, ViewerConfig(source="capture", camera="cam00", tolerance=0), tmp_path / "a", False
    )
    assert [(v["width"], v["height"]) for v in full["sets"][0]["views"]] == [(96, 64)] * 2
    config = ViewerConfig(source="capture", camera="cam00", tolerance=0, display_size=48, bundle_mb=0.42)
    manifest = build_viewer(work, config, tmp_path / "b", False)
    views = manifest["sets"][0]["views"]
    assert [(v["width"], v["height"]) for v in views] == [(48, 32)] * 2
    assert manifest["build"]["bytes"] <= 0.42e6
    assert all(v["components"] < 12 for v in views)  # the budget, not the tolerance, set the count
    from lightstage.viewer.reference import Bundle

    bundle = Bundle(tmp_path / "b")
    for i, view in enumerate(views):
        group, camera = view["view_id"].split("/")
        frames = np.stack(
            [downscale(read_processed(work.frame(FrameId(group, camera, k)))[0], 48, 32) for k in range(12)]
        )
        back = bundle.compressed(0, i).reconstruct()
        err = np.linalg.norm(back - frames) / np.linalg.norm(frames)
        assert err == pytest.approx(view["relative_error"], rel=1e-3)
    assert (
        json.loads((tmp_path / "b" / "manifest.json").read_text())["build"]["key"]["config"]["bundle_mb"]
        == 0.42
    )
    with pytest.raises(LightstageError, match="--bundle-mb"):
        build_viewer(work, ViewerConfig(source="capture", bundle_mb=0.01), tmp_path / "c", False)
