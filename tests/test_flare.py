"""Flares per pixel, not per frame: flare scoring only where a light is in view, the per-frame flare and bulb mask
(object pixels the flare veils included), the broken-frame drop, the flag bit in the shards, no loss on flagged
rays, and evaluation with and without flagged pixels and on back-lit images alone."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from lightstage.cameras import PinholeCamera, look_at
from lightstage.ids import FrameId, ViewId
from lightstage.preprocess.broken import broken_frames
from lightstage.preprocess.config import PreprocessConfig
from lightstage.preprocess.flare import (
    flare_mask,
    flare_regions,
    flare_scores,
    flare_scores_in_view,
    light_pixels,
    radial_profile,
    view_flares,
)
from lightstage.records import shards as shard_records
from lightstage.records.shards import flags_flare, flags_saturated
from lightstage.training.config import LossConfig
from lightstage.training.flagged import flag_scores, is_backlit
from lightstage.training.losses import total_loss

FACTOR = 8
W, H = 240, 160  # processed frame; thumbnails 30 x 20
CUTOFF = 4.4


def _view(frames: int = 12, seed: int = 0):
    """A view's thumbnails: an object (disc, mask) lit differently by each light over a dark noisy background."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:H, 0:W]
    mask = (xx - 120) ** 2 + (yy - 80) ** 2 <= 45**2
    ty, tx = np.mgrid[0:20, 0:30]
    obj = (tx * 8 + 4 - 120) ** 2 + (ty * 8 + 4 - 80) ** 2 <= 45**2
    lum = rng.uniform(0.8e-3, 1.2e-3, (frames, 20, 30)).astype(np.float32)
    for k in range(frames):
        lum[k][obj] = 0.05 + 0.5 * (k % 4)
    sat = np.zeros_like(lum)
    return lum, sat, mask, obj, (tx * 8 + 4.0, ty * 8 + 4.0)


def _glow(centre, peak, sigma, grid):
    gx, gy = grid
    return (peak * np.exp(-((gx - centre[0]) ** 2 + (gy - centre[1]) ** 2) / (2 * sigma**2))).astype(
        np.float32
    )


def test_no_light_in_view_means_no_flare_however_bright_the_frame() -> None:
    """A saturated specular highlight, and a lit white object spilling over the whole frame: without a light in
    view they neither score nor get a mask (the ungated score does fire: the geometry is what stops it)."""
    lum, sat, mask, obj, _ = _view()
    lum[1][obj] = 0.4
    lum[1][9:11, 14:16] = 60.0  # a specular highlight, clipped
    sat[1][9:11, 14:16] = 1.0
    lum[2][:] = 0.8  # a lit white object filling the frame, beyond the mask
    centres = [None] * len(lum)
    raw = flare_scores(lum, sat, mask, 8, CUTOFF, FACTOR)
    assert raw[2] > 0.15  # what the frame-level score alone would reject
    gated = flare_scores_in_view(lum, sat, mask, 8, CUTOFF, FACTOR, centres)
    assert np.all(gated == 0.0)
    regions = flare_regions(lum, sat, mask, 8, FACTOR, centres, 0.05, 1e-4)
    assert all(r is None for r in regions)
    # with a light in view those frames would be flagged: the gate, not the levels, keeps them
    assert flare_regions(lum, sat, mask, 8, FACTOR, [(120.0, 80.0)] * len(lum), 0.05, 1e-4)[2] is not None


def test_flare_mask_covers_bulb_glow_and_the_veiled_object() -> None:
    lum, sat, mask, obj, grid = _view()
    centre = (170.0, 70.0)  # the bulb just right of the object
    k = 4  # a back-lit frame: the object is dark (0.05), so weak glare matters on it
    lum[k] += _glow(centre, 0.6, 24.0, grid)
    lum[k][8:10, 20:22] = 80.0  # the bulb, clipped
    sat[k][8:10, 20:22] = 1.0
    centres = [None] * len(lum)
    centres[k] = centre
    regions = flare_regions(lum, sat, mask, 8, FACTOR, centres, 0.05, 1e-4)
    assert [i for i, r in enumerate(regions) if r is not None] == [k]
    m = flare_mask(regions[k], (W, H), FACTOR)
    assert m.shape == (H, W)
    assert m[64:80, 160:176].all()  # the bulb's blocks
    assert m[70, 150] and m[70, 130]  # object pixels the flare veils, on the bulb's side
    assert not m[80, 30] and not m[150, 10]  # far from the flare
    glow = _glow(centre, 0.6, 24.0, (np.arange(W)[None] + 0.5, np.arange(H)[:, None] + 0.5))
    # what is left unflagged adds about veil x the frame's object level at most (rings are a block wide)
    assert glow[~m].max() < 2.0 * 0.05 * np.median(lum[k][obj])
    assert m[mask].mean() > 0.3  # much of the dark object is veiled
    scores = flare_scores_in_view(lum, sat, mask, 8, CUTOFF, FACTOR, centres)
    assert scores[k] > 0 and np.count_nonzero(scores) == 1


def test_policies_mask_keeps_and_drop_rejects() -> None:
    lum, sat, mask, _, grid = _view()
    lum[5] += _glow((200.0, 40.0), 2.0, 30.0, grid)
    lights = list(range(len(lum)))
    pixels = {5: (200.0, 40.0)}
    kept = view_flares(lum, sat, mask, lights, pixels, PreprocessConfig(), CUTOFF)
    assert kept.rejected == [] and list(kept.regions) == [5]
    dropped = view_flares(lum, sat, mask, lights, pixels, PreprocessConfig(flare_policy="drop"), CUTOFF)
    assert dropped.rejected == [5] and dropped.regions == {}


def test_radial_profile_is_non_increasing_and_fills_hidden_rings() -> None:
    prof = radial_profile(np.array([5.0, 1.0, 3.0, 0.5]), np.array([2, 3, 3, 5]))
    np.testing.assert_allclose(prof, [5.0, 5.0, 5.0, 2.0, 0.5, 0.5])


def test_light_pixels_from_nominal_geometry() -> None:
    R, t = look_at(np.array([0.0, -1.5, 0.0]), np.zeros(3), np.array([0.0, 0.0, 1.0]))
    cam = PinholeCamera(np.array([[960.0, 0, 480], [0, 960, 320], [0, 0, 1]]), R, t, 960, 640)
    lights = np.array([[0.0, 1.5, 0.0], [0.0, -3.0, 0.0], [1.5, 0.0, 0.0], [0.05, 1.5, 0.0]])
    px = light_pixels(cam, lights, (240, 160), 0.1)
    assert px[0] == pytest.approx((120.0, 80.0)) and px[1] is None and px[2] is None
    assert px[3] is not None and px[3][0] > 120.0


def test_broken_frames_are_misfires_and_wrong_exposures_only() -> None:
    rng = np.random.default_rng(1)
    levels: dict[ViewId, dict[int, float]] = {}
    for g in range(9):
        for c in range(2):
            levels[ViewId(f"{40 * g:03d}", f"cam{c:02d}")] = {
                lt: float((1 + lt) * 0.01 * rng.uniform(0.8, 1.25)) for lt in range(6)
            }
    levels[ViewId("080", "cam01")][3] = 1e-7  # the light misfired: the dark level
    levels[ViewId("200", "cam00")][5] *= 4.0  # two stops too bright
    broken = broken_frames(levels, 6.0, 1.0)
    assert set(broken) == {FrameId("080", "cam01", 3), FrameId("200", "cam00", 5)}
    assert "misfired" in broken[FrameId("080", "cam01", 3)]
    few = {v: d for v, d in levels.items() if v.group in ("000", "040")}
    assert broken_frames(few, 6.0, 1.0) == {}  # two groups: nothing to compare with


def test_flagged_rays_carry_no_loss() -> None:
    n = 64
    g = torch.Generator().manual_seed(0)
    target = torch.rand(n, 3, generator=g) + 0.1
    flare = torch.zeros(n, dtype=torch.bool)
    flare[::4] = True
    batch = {
        "rgb": target,
        "saturated": torch.zeros(n, dtype=torch.bool),
        "zone": torch.full((n,), 2, dtype=torch.uint8),
        "flare": flare,
    }
    pred = target.clone()
    pred[flare] = 50.0  # glare the model would otherwise be taught
    out = {"rgb": pred, "sigma": torch.zeros(n, 4)}
    cfg = LossConfig()
    loss, parts = total_loss(out, batch, cfg)
    assert parts["rgb_fine"] == pytest.approx(0.0, abs=1e-12)
    unflagged = {k: v for k, v in batch.items() if k != "flare"}
    assert total_loss(out, unflagged, cfg)[1]["rgb_fine"] > 0.1
    batch["flare"] = torch.ones(n, dtype=torch.bool)
    assert float(total_loss(out, batch, cfg)[0]) == 0.0  # every ray flagged: nothing to learn, no NaN


def test_evaluation_with_and_without_flagged_pixels_and_backlit() -> None:
    R, t = look_at(np.array([0.0, -2.0, 0.0]), np.zeros(3), np.array([0.0, 0.0, 1.0]))
    cam = PinholeCamera(np.array([[40.0, 0, 16], [0, 40, 16], [0, 0, 1]]), R, t, 32, 32)
    target = np.full((32, 32, 3), 0.2, np.float32)
    flare = np.zeros((32, 32), bool)
    flare[4:12, 4:12] = True
    pred = target.copy()
    pred[flare] = 3.0  # wrong only where the flare is
    img = shard_records.TestImage(
        "x", cam, np.array([0.0, 1.0, 0.0]), target, None, np.ones((32, 32), bool), None, flare
    )
    s = flag_scores(pred, img, 1.0)
    assert s["psnr_unflagged"] == float("inf") and s["ssim_unflagged"] < 1.0
    assert s["flagged_fraction"] == pytest.approx(64 / 1024) and s["backlit"]
    front = shard_records.TestImage("y", cam, np.array([0.0, -1.0, 0.2]), target)
    assert not is_backlit(front)


def test_flare_bit_in_shards_and_test_images(tmp_path) -> None:
    """A flagged frame's rays carry the flare bit exactly where its flare mask meets the object mask; the test image
    keeps the mask; the loader hands the bit over as `flare`."""
    from support.fixtures import make_synthetic_work

    from lightstage.dataset.loader import RayShardDataset
    from lightstage.dataset.shard_config import ShardConfig
    from lightstage.dataset.shards import run_shard
    from lightstage.dataset.split import SplitConfig, run_split
    from lightstage.frames import write_image
    from lightstage.records.processed import read_mask
    from lightstage.records.shards import load_manifest, read_test_image, read_test_index
    from lightstage.records.split import load_split

    work, _ = make_synthetic_work(tmp_path)
    run_split(work, SplitConfig("paper"), progress=False)
    split = load_split(work.split)
    train = sorted(split.train.frames(), key=str)[0]
    test = sorted(split.test.frames(), key=str)[0]
    flare = np.zeros((32, 48), bool)
    flare[:, 20:] = True
    for f in (train, test):
        write_image(work.flare_mask(f), flare.astype(np.uint8) * 255)
    run_shard(work, ShardConfig(rays_per_image=64, rays_per_shard=256, workers=1), progress=False)
    m = load_manifest(work.shards_dir)
    rays = np.concatenate([np.load(work.shards_dir / s["file"]) for s in m["shards"]])
    views = [ViewId(*v.split("/")) for v in m["views"]]
    mask = read_mask(work.mask(ViewId(train.group, train.camera)))
    flagged = 0
    for r in rays:
        i, j = (int(x) for x in r["pixel"])
        v = views[r["view"]]
        inside = 0 <= i < 48 and 0 <= j < 32
        want = FrameId(v.group, v.camera, int(r["light"])) == train and inside and flare[j, i] and mask[j, i]
        assert bool(flags_flare(r["flags"])) == bool(want)
        flagged += bool(want)
    assert flagged > 0
    ds = RayShardDataset(work.shards_dir, 64)
    batch = ds.to_tensors(rays[:64])
    np.testing.assert_array_equal(batch["flare"].numpy(), flags_flare(rays[:64]["flags"]))
    np.testing.assert_array_equal(batch["saturated"].numpy(), flags_saturated(rays[:64]["flags"]))
    recs = read_test_index(work.shards_dir)
    rec = next(
        r for r in recs if (r["group"], r["camera"], r["light"]) == (test.group, test.camera, test.light)
    )
    img = read_test_image(work.shards_dir / rec["file"])
    np.testing.assert_array_equal(img.flare, flare)
    assert json.loads(work.report("shard").read_text())["rays"] == len(rays)


def test_frame_levels_leave_out_saturated_blocks() -> None:
    from lightstage.preprocess.flare import frame_levels

    lum = np.full((2, 4, 4), 0.1, np.float32)
    sat = np.zeros_like(lum)
    lum[0, 0, 0], sat[0, 0, 0] = 400.0, 1.0  # a clipped highlight or bulb: not the frame's level
    sat[1] = 1.0  # every block saturated: the plain mean
    np.testing.assert_allclose(frame_levels(lum, sat), [0.1, 0.1], rtol=1e-6)


def test_demo_report_shows_unflagged_and_backlit_rows() -> None:
    from lightstage.pipelines.demo_report import _eval_table

    ev = {
        "mean": {"psnr": 28.0, "psnr_unflagged": 29.5, "ssim_unflagged": 0.9},
        "backlit": {"count": 3, "mean": {"psnr": 24.25, "ssim": 0.8}},
    }
    text = "\n".join(_eval_table(ev))
    assert "without flare and bulb pixels | 29.50 | 0.9000" in text
    assert "back-lit test images only (3) | 24.25 | 0.8000" in text


def test_the_veil_is_centred_on_the_bulb_seen_not_the_nominal_one() -> None:
    """Nominal geometry 30 px off: the disc follows the clipped bulb in the frame."""
    from lightstage.preprocess.flare import bulb_centre

    lum, sat, mask, _, grid = _view()
    true = (180.0, 60.0)
    lum[4] += _glow(true, 0.6, 24.0, grid)
    lum[4][7:8, 22:23], sat[4][7:8, 22:23] = 80.0, 1.0  # the bulb: block (row 7, col 22), centre (180, 60)
    centres = [None] * len(lum)
    centres[4] = (208.0, 88.0)  # where stage.yaml puts it
    region = flare_regions(lum, sat, mask, 8, FACTOR, centres, 0.05, 1e-4)[4]
    assert region.centre == pytest.approx(true)
    assert bulb_centre(np.zeros((20, 30), bool), (1.0, 2.0), FACTOR) == (1.0, 2.0)  # hidden bulb: nominal
    assert flare_mask(region, (W, H), FACTOR)[62, 148]  # the veiled object on the bulb's side
