"""Scene bounds and ray shards on a synthesized work directory (sphere object, nominal calibration)."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
import torch
from support.fixtures import SPHERE_CENTRE, SPHERE_RADIUS, make_synthetic_work

from lightstage.cameras import pixel_rays
from lightstage.dataset.bounds import BoundsConfig, load_bounds, run_bounds
from lightstage.dataset.ray_table import RayTable
from lightstage.dataset.shard_config import ShardConfig
from lightstage.dataset.shard_rays import sampling_zones, view_rays
from lightstage.dataset.shards import run_shard, verify_shards
from lightstage.dataset.split import SplitConfig, run_split
from lightstage.errors import LightstageError
from lightstage.frames import read_exr
from lightstage.ids import FrameId, ViewId
from lightstage.pipelines.cli import main
from lightstage.records.calibration import Calibration
from lightstage.records.shards import RAY_DTYPE, flags_saturated, flags_zone, load_manifest
from lightstage.records.split import load_split
from lightstage.workdir import ZONE_BACKGROUND, ZONE_BAND, ZONE_FOREGROUND, WorkDir

CFG = ShardConfig(rays_per_image=64, rays_per_shard=256, workers=1, border_px=4)


@pytest.fixture(scope="module")
def sharded(tmp_path_factory):
    root = tmp_path_factory.mktemp("shards")
    work, stage = make_synthetic_work(root)
    run_split(work, SplitConfig("paper"), progress=False)
    summary = run_shard(work, CFG, progress=False)
    return work, stage, summary


def _all_rays(work):
    m = load_manifest(work.shards_dir)
    return m, [np.load(work.shards_dir / s["file"]) for s in m["shards"]]


def test_manifest_and_shards_keep_every_sampled_ray(sharded):
    """Every sampled ray lands in exactly one shard; shards hold ~rays_per_shard rays each, differ by at most
    one ray per zone, and keep the global 4:3:1 composition in fg | band | bg blocks."""
    work, _, summary = sharded
    m, shards = _all_rays(work)
    assert summary["shards"] == len(shards) >= 2
    sampled = m["sampled_zone_counts"]
    assert m["zone_counts"] == sampled == {"foreground": 32 * 18, "band": 24 * 18, "background": 8 * 18}
    assert sum(len(s) for s in shards) == m["rays"] == 64 * 18
    assert len(shards) == round(m["rays"] / 256)
    for s, rec in zip(shards, m["shards"], strict=True):
        assert s.dtype == RAY_DTYPE and RAY_DTYPE.itemsize == 16
        fg, band, bg = (rec["zones"][k] for k in ("foreground", "band", "background"))
        for n, total in zip((fg, band, bg), sampled.values(), strict=True):
            assert abs(n - total / len(shards)) < 1
        # blocks: foreground | band | background
        z = flags_zone(s["flags"])
        assert (z[:fg] == ZONE_FOREGROUND).all() and (z[fg : fg + band] == ZONE_BAND).all()
        assert (z[fg + band :] == ZONE_BACKGROUND).all()
        assert len(set(s["view"].tolist())) > 1  # shuffled across images
    every = np.concatenate(shards)
    fg = every[flags_zone(every["flags"]) == ZONE_FOREGROUND]
    keys = np.column_stack([fg["view"], fg["light"], fg["pixel"]]).astype(np.int64)
    assert len(np.unique(keys, axis=0)) == len(fg)  # no foreground ray twice (drawn without repetition)
    assert 16 <= summary["bytes_per_ray"] < 17  # 16 bytes a ray + a 128-byte npy header per 256-ray shard
    n = m["normalization"]
    assert n["scale"] > 0 and len(n["centre"]) == 3
    assert json.loads(work.report("shard").read_text())["rays"] == m["rays"]


def test_round_trip_rays_rederived_from_calibration(sharded):
    work, stage, _ = sharded
    m, shards = _all_rays(work)
    calib = Calibration.load(work.calibration)
    split = load_split(work.split)
    train = set(split.train.frames())
    rays = np.concatenate(shards)
    table = RayTable(m)  # the rays as the loader computes them from the manifest's camera and light tables
    origin, direction, light_position, light_direction = (
        x.numpy()
        for x in table.rays(
            torch.from_numpy(rays["view"].astype(np.int64)),
            torch.from_numpy(rays["light"].astype(np.int64)),
            torch.from_numpy(rays["pixel"].astype(np.int64)),
        )
    )
    views = [ViewId(*v.split("/")) for v in m["views"]]
    border = 0
    for v_idx in np.unique(rays["view"]):
        v = views[v_idx]
        cam = calib.views[v].camera()
        at = rays["view"] == v_idx
        sel = rays[at]
        pix = sel["pixel"].astype(np.int64)
        o, d = view_rays(cam.K, cam.R, cam.t, cam.dist, pix)
        np.testing.assert_array_equal(origin[at], o)
        np.testing.assert_array_equal(direction[at], d)
        o2, d2 = pixel_rays(pix + 0.5, cam.K, cam.R, cam.t)  # the convention module, directly
        np.testing.assert_array_equal(direction[at], d2.astype(np.float32))
        np.testing.assert_array_equal(origin[at], o2.astype(np.float32))
        lp = calib.light_positions[v.group][sel["light"]]
        np.testing.assert_array_equal(light_position[at], lp.astype(np.float32))
        ld = calib.light_directions(v.group)[sel["light"]]
        np.testing.assert_array_equal(light_direction[at], ld.astype(np.float32))
        import cv2

        mask = cv2.imread(str(work.mask(v)), cv2.IMREAD_UNCHANGED) > 0
        zones = sampling_zones(mask, CFG.band_fraction)  # the shard stage's zones: mask + outer band
        for r in sel:
            f = FrameId(v.group, v.camera, int(r["light"]))
            assert f in train
            i, j = (int(x) for x in r["pixel"])
            if 0 <= i < cam.width and 0 <= j < cam.height:
                img = read_exr(work.frame(f), channels="RGBS")
                assert flags_zone(r["flags"]) == zones[j, i]
                want = img[j, i, :3] if mask[j, i] else np.zeros(3, np.float16)
                np.testing.assert_array_equal(r["rgb"], want)
                assert bool(flags_saturated(r["flags"])) == bool(mask[j, i] and img[j, i, 3] > 0.5)
            else:
                border += 1
                assert flags_zone(r["flags"]) == ZONE_BACKGROUND and not r["rgb"].any()
                assert not flags_saturated(r["flags"])
    assert border > 0  # the padded border outside the image is sampled


def test_test_images_and_no_leak(sharded):
    work, _, summary = sharded
    split = load_split(work.split)
    m, shards = _all_rays(work)
    rays = np.concatenate(shards)
    test_lights = split.test.lights()
    assert not set(rays["light"].tolist()) & test_lights
    assert not {m["views"][v].split("/")[1] for v in np.unique(rays["view"])} & split.test.cameras()
    assert summary["test_images"] == split.test.count()
    calib = Calibration.load(work.calibration)
    for f in split.test.frames():
        d = np.load(work.shards_dir / "test" / f"{f.group}_{f.camera}_{f.light:03d}.npz")
        img = read_exr(work.frame(f), channels="RGBS")
        np.testing.assert_array_equal(d["rgb"], img[..., :3])
        cam = calib.views[ViewId(f.group, f.camera)].camera()
        np.testing.assert_array_equal(d["K"], cam.K)
        np.testing.assert_array_equal(d["R"], cam.R)
        np.testing.assert_allclose(d["light_position"], calib.light_positions[f.group][f.light])


def test_rerun_is_skipped_and_corruption_detected(sharded, tmp_path):
    work, _, _ = sharded
    assert run_shard(work, CFG, progress=False)["skipped"]
    assert verify_shards(work.shards_dir) >= 2
    copy = tmp_path / "shards"
    shutil.copytree(work.shards_dir, copy)
    m = load_manifest(copy)
    path = copy / m["shards"][1]["file"]
    data = bytearray(path.read_bytes())
    data[-100] ^= 0x01
    path.write_bytes(bytes(data))
    with pytest.raises(LightstageError, match="checksum mismatch"):
        verify_shards(copy)
    path.write_bytes(bytes(data[:-64]))
    with pytest.raises(LightstageError, match="truncated"):
        verify_shards(copy)


def test_cli_shard_and_bounds_errors(tmp_path, capsys):
    assert main(["shard", str(tmp_path / "nowork")]) == 2
    assert "nowork: work directory not found" in capsys.readouterr().err


def test_bounds_contain_the_object_and_are_tight(tmp_path):
    work, _ = make_synthetic_work(tmp_path, num_cameras=6, num_lights=1, num_groups=3)
    s = run_bounds(work, BoundsConfig(resolution=48), progress=False)
    b = load_bounds(work.bounds)
    lo, hi = SPHERE_CENTRE - SPHERE_RADIUS, SPHERE_CENTRE + SPHERE_RADIUS
    assert np.all(b.box_min <= lo + 1e-9) and np.all(b.box_max >= hi - 1e-9)
    assert np.all(b.box_max - b.box_min < 2 * SPHERE_RADIUS * 1.6), (b.box_min, b.box_max)
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    assert np.abs(b.normalize(corners)).max() <= 1.0 / 1.1 + 1e-9
    assert s["views"] == 18
    assert run_bounds(work, BoundsConfig(resolution=48), progress=False)["skipped"]
    assert not run_bounds(work, BoundsConfig(resolution=40), progress=False)["skipped"]


def _sharded_copy(root, config, executor=None):
    work, _ = make_synthetic_work(root)
    run_split(work, SplitConfig("paper"), progress=False)
    run_shard(work, config, executor, progress=False)
    return load_manifest(work.shards_dir)


def test_parallel_local_pool_writes_identical_shards(sharded, tmp_path):
    work, _, _ = sharded
    ref = load_manifest(work.shards_dir)
    m = _sharded_copy(tmp_path, ShardConfig(rays_per_image=64, rays_per_shard=256, workers=2, border_px=4))
    assert [s["sha256"] for s in m["shards"]] == [s["sha256"] for s in ref["shards"]]


@pytest.mark.slow
def test_dask_client_writes_identical_shards(sharded, tmp_path):
    from lightstage.dask_executor import dask_executor

    work, _, _ = sharded
    ref = load_manifest(work.shards_dir)
    with dask_executor(workers=2, verbose=False) as executor:
        m = _sharded_copy(tmp_path, CFG, executor)
    assert [s["sha256"] for s in m["shards"]] == [s["sha256"] for s in ref["shards"]]


@pytest.mark.slow
def test_tiny_simulated_capture_end_to_end(tiny_capture, tmp_path):
    """Simulator tiny capture -> preprocess -> ground-truth calibration -> split -> bounds -> shards -> loader."""
    run_mod = pytest.importorskip("lightstage.preprocess.run")
    from lightstage.dataset.loader import RayShardDataset
    from lightstage.preprocess.config import PreprocessConfig

    work = WorkDir.at(tmp_path / "work")
    work.root.mkdir()
    work.capture_pointer.write_text(str(tiny_capture))
    run_mod.run_preprocess(work, PreprocessConfig(), progress=False)
    work.calibration.parent.mkdir(parents=True, exist_ok=True)
    shutil.copy(tiny_capture / "ground_truth" / "geometry.json", work.calibration)
    counts = run_split(work, SplitConfig("paper"), progress=False)["counts"]
    rejected = json.loads(work.report("preprocess").read_text()).get("rejected_frames", [])
    assert counts["train"] + counts["train_excluded"] == 9 * 3 * 3
    assert counts["train_excluded"] + counts["test_excluded"] <= len(rejected)
    run_bounds(work, BoundsConfig(), progress=False)
    b = load_bounds(work.bounds)
    truth = json.loads((tiny_capture / "ground_truth" / "scene.json").read_text())["object_bbox"]
    assert np.all(b.box_min <= np.array(truth["min"]) + 0.01) and np.all(
        b.box_max >= np.array(truth["max"]) - 0.01
    )
    s = run_shard(work, ShardConfig(rays_per_shard=4096, workers=1), progress=False)
    assert s["rays"] > 0 and s["test_images"] == counts["test"]
    batch = next(iter(RayShardDataset(work.shards_dir, batch_size=1024)))
    assert batch["rgb"][:512].mean() > 0  # foreground rays carry light
    assert (batch["rgb"][-128:] == 0).all()  # background target 0


def test_cli_and_changed_config_rewrites(tmp_path, capsys):
    m0 = _sharded_copy(tmp_path, CFG)
    work = tmp_path / "work"
    assert (work / "bounds.png").is_file()
    assert (
        main(["shard", str(work), "--rays-per-image", "64", "--rays-per-shard", "256", "--workers", "1"]) == 0
    )
    out = capsys.readouterr().out
    assert "rays in" in out and "bytes/ray" in out
    assert main(["shard", str(work), "--verify"]) == 0
    assert "verified" in capsys.readouterr().out
    # another seed: every shard is rewritten (no stale shard of the old plan is reused)
    s = run_shard(
        WorkDir.at(work),
        ShardConfig(rays_per_image=64, rays_per_shard=256, workers=1, border_px=4, seed=1),
        progress=False,
    )
    assert not s["skipped"]
    m1 = load_manifest(work / "shards")
    assert not {r["sha256"] for r in m1["shards"]} & {r["sha256"] for r in m0["shards"]}
    assert verify_shards(work / "shards") == len(m1["shards"])


def test_view_rays_undistort_distorted_cameras():
    """A ray of a distorted camera re-projects (with the distortion) onto its pixel centre."""
    import cv2

    from lightstage.cameras import look_at

    K = np.array([[120.0, 0, 64], [0, 120.0, 40], [0, 0, 1]])
    R, t = look_at(np.array([0.0, -1.5, 0.3]), np.zeros(3))
    dist = np.array([-0.12, 0.03, 0.001, -0.002, 0.0])
    pix = np.array([[0, 0], [10, 70], [127, 79], [64, 40], [-20, 5]])
    o, d = view_rays(K, R, t, dist, pix)
    pts = o.astype(np.float64) + 2.0 * d.astype(np.float64)
    uv, _ = cv2.projectPoints(pts, cv2.Rodrigues(R)[0], t, K, dist)
    np.testing.assert_allclose(uv.reshape(-1, 2), pix + 0.5, atol=2e-3)


def test_bounds_recomputed_when_masks_change(tmp_path):
    import cv2

    work, _ = make_synthetic_work(tmp_path, num_cameras=4, num_lights=1, num_groups=2)
    cfg = BoundsConfig(resolution=32)
    first = run_bounds(work, cfg, progress=False)
    assert run_bounds(work, cfg, progress=False)["skipped"]
    v = ViewId("000", "cam00")
    m = cv2.imread(str(work.mask(v)), cv2.IMREAD_UNCHANGED)
    cv2.imwrite(str(work.mask(v)), np.zeros_like(m) + 255 * (np.arange(m.shape[1]) < m.shape[1] // 2))
    again = run_bounds(work, cfg, progress=False)
    assert not again["skipped"] and again["centre"] != first["centre"]


@pytest.mark.parametrize("size", [(48, 32), (32, 48), (40, 40)])
@pytest.mark.parametrize("border", [0, 3])
def test_border_ring_enumerates_every_outside_pixel_once(size, border):
    from lightstage.dataset.shard_rays import border_geometry, border_pixels, ring_size

    w, h = size
    pad = border_geometry(w, h, ShardConfig(border_px=border))
    n = ring_size(w, h, pad)
    if w == h and border == 0:
        assert n == 0  # a square image without margin has no ring
        return
    pix = border_pixels(np.arange(n), w, h, pad)
    assert len({tuple(p) for p in pix.tolist()}) == n
    inside = (pix[:, 0] >= 0) & (pix[:, 0] < w) & (pix[:, 1] >= 0) & (pix[:, 1] < h)
    assert not inside.any()
    assert pix[:, 0].min() >= -pad[0] and pix[:, 0].max() < w + pad[0]
    assert pix[:, 1].min() >= -pad[1] and pix[:, 1].max() < h + pad[1]
    assert n == (w + 2 * pad[0]) * (h + 2 * pad[1]) - w * h
    if border == 0 and w != h:
        assert (w + 2 * pad[0]) - (h + 2 * pad[1]) in (0, 1, -1)  # padded to (about) a square


def test_default_sampling_covers_every_foreground_pixel_once(tmp_path):
    """rays_per_image 0 (default): every mask pixel of every training frame is one foreground ray of the epoch,
    with 3/4 as many band rays (inside the outer band) and 1/4 as many background rays."""
    import cv2

    work, _ = make_synthetic_work(tmp_path)
    run_split(work, SplitConfig("paper"), progress=False)
    run_shard(work, ShardConfig(rays_per_shard=4096, workers=1, border_px=4), progress=False)
    m, shards = _all_rays(work)
    rays = np.concatenate(shards)
    views = [ViewId(*v.split("/")) for v in m["views"]]
    frames = 0
    for v_idx in np.unique(rays["view"]):
        mask = cv2.imread(str(work.mask(views[v_idx])), cv2.IMREAD_UNCHANGED) > 0
        zones = sampling_zones(mask, ShardConfig().band_fraction)
        for light in np.unique(rays["light"][rays["view"] == v_idx]):
            sel = rays[(rays["view"] == v_idx) & (rays["light"] == light)]
            fg = sel[flags_zone(sel["flags"]) == ZONE_FOREGROUND]["pixel"]
            got = np.zeros_like(mask)
            got[fg[:, 1], fg[:, 0]] = True
            assert len(fg) == mask.sum() and (got == mask).all()
            band = sel[flags_zone(sel["flags"]) == ZONE_BAND]["pixel"]
            assert (
                len(band) == round(0.75 * mask.sum()) and (zones[band[:, 1], band[:, 0]] == ZONE_BAND).all()
            )
            assert (flags_zone(sel["flags"]) == ZONE_BACKGROUND).sum() == round(0.25 * mask.sum())
            frames += 1
    assert frames == m["frames"]
