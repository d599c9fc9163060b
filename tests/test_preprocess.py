"""Preprocess: exact downscale, saturation flags, streaming/tree-merged statistics, segmentation IoU on the
simulator, bad frames, and resuming a killed run with identical outputs."""

from __future__ import annotations

import dataclasses
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import yaml

from lightstage.capture.layout import open_capture
from lightstage.errors import LightstageError
from lightstage.exr_header import read_exr_header
from lightstage.frames import write_exr, write_exr_planes
from lightstage.ids import FrameId, ViewId
from lightstage.preprocess.config import PreprocessConfig
from lightstage.preprocess.downscale import (
    decode_downscale,
    decode_raw,
    downscale,
    downscale_reference,
    saturation_half,
)
from lightstage.preprocess.run import run_preprocess
from lightstage.preprocess.stats import StatsAccumulator, direct_stats, merge_tree
from lightstage.records.processed import (
    HalfRounder,
    processed_ok,
    read_processed,
    read_processed_half,
    write_processed,
)
from lightstage.workdir import ZONE_BACKGROUND, ZONE_BAND, ZONE_FOREGROUND, WorkDir

CUTOFF = 4.4019


def _frame(rng: np.random.Generator, h: int, w: int, dtype=np.float16) -> np.ndarray:
    """Wide dynamic range test frame: exponentially distributed values, some clipped at the cutoff."""
    x = rng.exponential(0.3, (h, w, 3)) * rng.choice([1e-3, 1.0, 20.0], (h, w, 1), p=[0.3, 0.6, 0.1])
    x = np.minimum(x, float(saturation_half(CUTOFF)))
    return x.astype(dtype)


# ---- downscale ------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("dtype", [np.float16, np.float32])
def test_downscale_equals_float64_box_mean(dtype) -> None:
    rng = np.random.default_rng(1)
    px = _frame(rng, 72, 96, dtype)  # 72 rows: not a multiple of the band height below
    out = downscale(px, CUTOFF, band_rows=16)
    ref = downscale_reference(px, CUTOFF)
    assert out.rgb.shape == (18, 24, 3) and out.rgb.dtype == np.float32
    # float32 sums of 16 samples: relative error at float32 rounding level, far below half precision
    np.testing.assert_allclose(out.rgb, ref.rgb, rtol=2e-7, atol=0)
    np.testing.assert_array_equal(out.saturated, ref.saturated)
    assert out.saturated.any() and not out.saturated.all()


def test_saturation_flags_any_of_sixteen_samples() -> None:
    px = np.full((16, 16, 3), 0.5, np.float16)
    cut = saturation_half(CUTOFF)
    assert float(cut) >= CUTOFF and float(np.nextafter(cut, np.float16(0))) < CUTOFF
    px[5, 9, 2] = cut  # exactly the smallest half >= cutoff, blue only: block (1, 2)
    px[14, 0, 0] = np.nextafter(cut, np.float16(0))  # just below: not saturated
    px[0, 15, 1] = 60000.0  # far above (bulb): block (0, 3)
    out = downscale(px, CUTOFF)
    expected = np.zeros((4, 4), bool)
    expected[1, 2] = expected[0, 3] = True
    np.testing.assert_array_equal(out.saturated, expected)
    np.testing.assert_array_equal(downscale(px.astype(np.float32), CUTOFF).saturated, expected)


@pytest.mark.parametrize(
    "dtype, channels, band_rows",
    [(np.float16, "RGB", 64), (np.float16, "RGBA", 24), (np.float32, "RGB", 40), (np.float16, "BGR", 16)],
)
def test_band_decoder_equals_whole_frame_decode(tmp_path: Path, dtype, channels: str, band_rows: int) -> None:
    """The stage's streaming decoder (OIIO scanline bands) gives exactly the whole-frame decode + downscale,
    whatever the channel set/order and whether the band height divides the frame."""
    rng = np.random.default_rng(7)
    rgb = _frame(rng, 72, 96, dtype)
    planes = {"R": rgb[..., 0], "G": rgb[..., 1], "B": rgb[..., 2], "A": np.ones_like(rgb[..., 0])}
    path = tmp_path / "raw.exr"
    write_exr(path, np.stack([planes[c] for c in channels], -1), half=dtype == np.float16, channels=channels)
    streamed = decode_downscale(path, (96, 72), CUTOFF, band_rows=band_rows)
    whole = downscale(np.asarray(decode_raw(path, (96, 72))), CUTOFF)
    np.testing.assert_array_equal(streamed.rgb, whole.rgb)
    np.testing.assert_array_equal(streamed.saturated, whole.saturated)
    assert streamed.saturated.any()


def test_band_decoder_names_file_and_rows_of_corrupt_pixel_data(tmp_path: Path) -> None:
    rng = np.random.default_rng(8)
    path = tmp_path / "raw.exr"
    write_exr(path, _frame(rng, 344, 512), compression="zip")
    data = bytearray(path.read_bytes())
    at = len(data) // 2
    data[at : at + 200] = bytes(200)  # zeroed bytes inside a compressed chunk (zlib's checksum fails)
    path.write_bytes(bytes(data))
    with pytest.raises(LightstageError, match=r"raw\.exr: corrupt EXR pixel data in rows \d+-\d+"):
        decode_downscale(path, (512, 344), CUTOFF)
    with pytest.raises(LightstageError, match="resolution 512x344, expected 512x340"):
        decode_downscale(path, (512, 340), CUTOFF)


@pytest.mark.parametrize("compression", ["zip", "piz", "rle", "none"])
def test_processed_frame_roundtrip_and_validity(tmp_path: Path, compression: str) -> None:
    rng = np.random.default_rng(2)
    d = downscale(_frame(rng, 32, 48), CUTOFF)
    expected = d.rgb.astype(np.float16)
    path = tmp_path / "f.exr"
    planes = HalfRounder(8, 12)(d.rgb)  # rounds d.rgb in place to what is stored
    np.testing.assert_array_equal(planes, expected.transpose(2, 0, 1))
    np.testing.assert_array_equal(d.rgb, expected.astype(np.float32))
    write_processed(path, planes, d.saturated, compression)
    rgb, sat = read_processed(path, (12, 8))
    np.testing.assert_array_equal(rgb, expected.astype(np.float32))
    np.testing.assert_array_equal(sat, d.saturated)
    assert processed_ok(path, (12, 8))
    assert not processed_ok(path, (12, 9))  # wrong size
    data = path.read_bytes()
    (tmp_path / "cut.exr").write_bytes(data[: len(data) // 2])  # what a non-atomic killed write would leave
    assert not processed_ok(tmp_path / "cut.exr", (12, 8))
    assert not processed_ok(tmp_path / "absent.exr", (12, 8))


def test_processed_frame_layout_is_two_tiled_parts_and_the_older_layout_still_reads(tmp_path: Path) -> None:
    """Colour and flags are separate parts (each its own compression) in tiles; one-part scanline RGBS frames
    (the layout before the tiled one) read the same, and a frame without flags is refused by name."""
    rng = np.random.default_rng(5)
    h, w = 300, 520  # more than one tile each way, partial tiles at the edges
    planes = rng.lognormal(-2, 1, (3, h, w)).astype(np.float16)
    sat = rng.random((h, w)) < 0.01
    path = tmp_path / "f.exr"
    write_processed(path, planes, sat, "none", attributes={"source": "raw.exr"})
    header = read_exr_header(path)
    assert header.parts == 2 and header.tiled
    assert header.part_channels == (("B", "G", "R"), ("S",))
    assert header.attributes["source"] == "raw.exr"
    rgb, flags = read_processed_half(path, (w, h))
    np.testing.assert_array_equal(rgb, planes.transpose(1, 2, 0))
    np.testing.assert_array_equal(flags, sat)

    legacy = tmp_path / "legacy.exr"
    old = {c: np.ascontiguousarray(planes[i]) for i, c in enumerate("RGB")}
    write_exr_planes(legacy, {**old, "S": sat.astype(np.float16)}, compression="rle")
    assert read_exr_header(legacy).parts == 1 and processed_ok(legacy, (w, h))
    rgb, flags = read_processed_half(legacy, (w, h))
    np.testing.assert_array_equal(rgb, planes.transpose(1, 2, 0))
    np.testing.assert_array_equal(flags, sat)

    no_flags = tmp_path / "no_flags.exr"
    write_exr_planes(no_flags, old, compression="none")
    assert not processed_ok(no_flags, (w, h))
    with pytest.raises(LightstageError, match=r"no_flags\.exr: processed frame lacks channel\(s\) S"):
        read_processed_half(no_flags, (w, h))


# ---- statistics -------------------------------------------------------------------------------------------------
def test_streaming_stats_equal_direct_and_tree_merge_equals_whole() -> None:
    rng = np.random.default_rng(3)
    k, h, w = 11, 9, 13
    frames = [(_frame(rng, h, w).astype(np.float32)) for _ in range(k)]
    sats = [rng.random((h, w)) < 0.05 for _ in range(k)]
    taus = list(rng.uniform(0.05, 0.2, k))
    lights = list(range(k))
    ref = direct_stats(frames, sats, taus, lights)

    def accumulate(idx: list[int]):
        acc = StatsAccumulator(h, w)
        for i in idx:
            acc.add(i, frames[i], sats[i], taus[i])
        return acc.finish()

    whole = accumulate(lights)
    tree = merge_tree(accumulate(lights[i : i + 3]) for i in range(0, k, 3))
    for s in (whole, tree):
        assert s.count == k and s.lights == tuple(lights)
        np.testing.assert_allclose(s.mean, ref.mean, rtol=1e-6, atol=1e-7)
        np.testing.assert_allclose(s.variance, ref.variance, rtol=1e-4, atol=1e-6)
        np.testing.assert_allclose(s.peak, ref.peak, rtol=1e-6)
        np.testing.assert_array_equal(s.saturated, ref.saturated)
        np.testing.assert_array_equal(s.lit, ref.lit)
        np.testing.assert_allclose(s.lum_sum, ref.lum_sum, rtol=1e-5, atol=1e-6)
    # a different tree over the same lights agrees too; overlapping sets are refused
    other = accumulate([0, 5, 9]).merge(accumulate([1, 2, 3, 4, 6, 7, 8, 10]))
    np.testing.assert_allclose(other.mean, whole.mean, rtol=1e-6, atol=1e-7)
    np.testing.assert_allclose(other.m2, whole.m2, rtol=1e-4, atol=1e-6)
    with pytest.raises(LightstageError, match="overlap"):
        accumulate([0, 1]).merge(accumulate([1, 2]))


def test_ladder_counts_equal_direct_at_level_edges_and_past_255_frames(tmp_path: Path) -> None:
    """The accumulator's ladder (level index from float bits, uint8 counts widened every 255 frames) counts
    exactly what `direct_stats` counts with float compares: luminances on, just above and just below each
    level, negatives, -0.0 and saturated pixels; a partial saved from `finish(reuse=True)` loads the same."""
    from lightstage.preprocess.stats import ViewStats, ladder_levels

    rng = np.random.default_rng(4)
    h, w, k = 6, 40, 300
    levels = ladder_levels(CUTOFF)
    edge = np.concatenate([levels, np.nextafter(levels, np.float32(0)), np.nextafter(levels, np.float32(9))])
    frames, sats = [], []
    for _ in range(k):
        grey = rng.choice(edge, (h, w)).astype(np.float32)  # luminance of a grey pixel is its value
        grey[0, :4] = [-0.0, -1e-3, 0.0, CUTOFF * 2]
        frames.append(np.repeat(grey[..., None], 3, axis=-1))
        sats.append(rng.random((h, w)) < 0.1)
    taus = list(rng.uniform(0.0, 0.01, k))
    lum = [f[..., 0] for f in frames]  # exact: LUMA's weights sum to one only approximately
    acc = StatsAccumulator(h, w, CUTOFF)
    for i in range(k):
        acc.add(i, frames[i], sats[i], taus[i], lum[i])
    ref = np.stack([(np.stack(lum) > lv) & ~np.stack(sats) for lv in levels]).sum(axis=1)
    whole = acc.finish()
    np.testing.assert_array_equal(whole.ladder, ref)
    assert whole.ladder.dtype == np.uint16
    np.testing.assert_array_equal(
        whole.ladder, direct_stats(frames, sats, taus, list(range(k)), CUTOFF).ladder
    )
    for n in (5, k):  # uint8 counts (no widening yet) and widened ones
        acc = StatsAccumulator(h, w, CUTOFF)
        for i in range(n):
            acc.add(i, frames[i], sats[i], taus[i], lum[i])
        copied = acc.finish()
        acc.finish(reuse=True).save(tmp_path / "p.npz")
        loaded = ViewStats.load(tmp_path / "p.npz")
        for key, value in copied.arrays().items():
            assert loaded.arrays()[key].dtype == value.dtype, key
            np.testing.assert_array_equal(loaded.arrays()[key], value)
        with pytest.raises(LightstageError, match="already finished"):
            acc.add(0, frames[0], sats[0], taus[0])


def test_merge_tree_in_place_equals_merge_tree_bit_for_bit() -> None:
    """The view task merges the partials it loaded in place (consume=True): the same bits as fresh arrays."""
    rng = np.random.default_rng(7)
    h, w, k = 9, 13, 11
    frames = [_frame(rng, h, w).astype(np.float32) for _ in range(k)]
    sats = [rng.random((h, w)) < 0.05 for _ in range(k)]

    def parts():
        for i in range(0, k, 2):
            acc = StatsAccumulator(h, w, CUTOFF)
            for j in range(i, min(i + 2, k)):
                acc.add(j, frames[j], sats[j], 0.1)
            yield acc.finish(reuse=True)

    fresh, in_place = merge_tree(parts()), merge_tree(parts(), consume=True)
    for key, value in fresh.arrays().items():
        assert in_place.arrays()[key].dtype == value.dtype, key
        assert in_place.arrays()[key].tobytes() == value.tobytes(), key


def test_downscale_into_reused_buffers_equals_fresh() -> None:
    """A chunk task decodes each frame into the same arrays: flags of the previous frame must not survive."""
    rng = np.random.default_rng(6)
    first, second = _frame(rng, 32, 48), np.full((32, 48, 3), 0.25, np.float16)
    out = (np.empty((8, 12, 3), np.float32), np.empty((8, 12), bool))
    downscale(first, CUTOFF, band_rows=8, out=out)
    assert out[1].any()
    d = downscale(second, CUTOFF, band_rows=8, out=out)
    assert d.rgb is out[0] and d.saturated is out[1]
    fresh = downscale(second, CUTOFF, band_rows=8)
    np.testing.assert_array_equal(d.rgb, fresh.rgb)
    np.testing.assert_array_equal(d.saturated, fresh.saturated)
    with pytest.raises(LightstageError, match="output buffers do not fit"):
        downscale(first, CUTOFF, out=(np.empty((8, 12, 3), np.float64), out[1]))


def test_config_from_dict_names_bad_keys() -> None:
    assert PreprocessConfig.from_dict({"flare_threshold": 1, "compression": "piz"}).flare_threshold == 1.0
    with pytest.raises(LightstageError, match=r"^p\.yaml: unknown key 'nope' \(known: compression, "):
        PreprocessConfig.from_dict({"nope": 1}, "p.yaml")
    with pytest.raises(LightstageError, match="^band_width: expected an integer, got 'wide'"):
        PreprocessConfig.from_dict({"band_width": "wide"})
    with pytest.raises(LightstageError, match="^compression: expected one of"):
        PreprocessConfig.from_dict({"compression": "dwaa"})


# ---- whole stage on the simulator -------------------------------------------------------------------------------
def _subset_capture(src: Path, dst: Path, groups: int, cameras: int) -> Path:
    """A capture with the first groups/cameras of `src` (frames copied, so they can be damaged)."""
    cap = open_capture(src)
    stage = dataclasses.replace(
        cap.stage, groups=cap.stage.groups[:groups], cameras=cap.stage.cameras[:cameras]
    )
    dst.mkdir(parents=True)
    plain = json.loads(json.dumps(stage.to_dict(), default=float))  # numpy scalars -> plain floats
    (dst / "stage.yaml").write_text(yaml.safe_dump(plain, sort_keys=False))
    shutil.copy(src / "capture.yaml", dst / "capture.yaml")
    for v in open_capture(dst).views():
        shutil.copytree(src / "frames" / v.group / v.camera, dst / "frames" / v.group / v.camera)
        gt = src / "ground_truth" / "masks" / v.group / f"{v.camera}.png"
        (dst / "ground_truth" / "masks" / v.group).mkdir(parents=True, exist_ok=True)
        shutil.copy(gt, dst / "ground_truth" / "masks" / v.group / gt.name)
    return dst


def _work(tmp: Path, capture: Path) -> WorkDir:
    work = WorkDir.at(tmp)
    work.root.mkdir(parents=True, exist_ok=True)
    work.capture_pointer.write_text(str(capture) + "\n")
    return work


@pytest.fixture(scope="module")
def tiny_run(tiny_capture: Path, tmp_path_factory: pytest.TempPathFactory) -> tuple[WorkDir, dict]:
    work = _work(tmp_path_factory.mktemp("work"), tiny_capture)
    summary = run_preprocess(work, PreprocessConfig(), progress=False)
    return work, summary


def test_segmentation_iou_against_ground_truth_on_tiny(tiny_run) -> None:
    work, summary = tiny_run
    report = json.loads(work.report("preprocess").read_text())
    seg = report["segmentation"]
    # tiny is 64x43 after downscaling: a one-pixel boundary error is several % of IoU here
    assert seg["iou_mean"] >= 0.95, seg
    assert seg["iou_worst"] >= 0.90, seg
    assert summary["counts"]["processed"] == report["counts"]["frames"] == 9 * 4 * 12
    assert report["problems"] == [] and report["errors"] == []


def test_outputs_of_a_view(tiny_run, tiny_capture: Path) -> None:
    import cv2

    from lightstage.frames import read_exr

    work, _ = tiny_run
    view = ViewId("040", "cam01")
    rgb, sat = read_processed(work.frame(FrameId("040", "cam01", 6)), (64, 43))
    assert rgb.shape == (43, 64, 3) and sat.shape == (43, 64)
    mask = cv2.imread(str(work.mask(view)), cv2.IMREAD_UNCHANGED)
    zones = cv2.imread(str(work.zones(view)), cv2.IMREAD_UNCHANGED)
    wellit = cv2.imread(str(work.wellit(view)), cv2.IMREAD_UNCHANGED)
    assert mask.dtype == np.uint8 and set(np.unique(mask)) == {0, 255}
    assert set(np.unique(zones)) == {ZONE_BACKGROUND, ZONE_BAND, ZONE_FOREGROUND}
    assert np.all(zones[mask == 0] != ZONE_FOREGROUND) and np.all(zones[mask == 255] != ZONE_BACKGROUND)
    assert wellit.shape == (43, 64, 3) and wellit.dtype == np.uint8 and wellit.max() > 100
    assert (work.view_dir(view) / "overlay.png").is_file()
    mean = read_exr(work.mean_image(view)).astype(np.float32)
    stack = [read_processed(work.frame(FrameId("040", "cam01", lt)))[0] for lt in range(12)]
    np.testing.assert_allclose(mean, np.mean(stack, axis=0), rtol=2e-3, atol=1e-6)  # half-rounded mean
    # the simulator's flares are found: strong flare frames score above every frame without a nuisance
    report = json.loads(work.report("preprocess").read_text())
    nuisances = json.loads((tiny_capture / "ground_truth" / "nuisances.json").read_text())
    flares = {(f["group"], f["camera"], f["light"]) for f in nuisances["flares"] if f["strength"] > 0.05}
    any_nuisance = {
        (f["group"], f["camera"], f["light"]) for f in nuisances["flares"] + nuisances["bulbs_in_view"]
    }
    scores = report["flare"]["scores"]
    clean = [
        s for v, d in scores.items() for lt, s in d.items() if (*v.split("/"), int(lt)) not in any_nuisance
    ]
    flared = [scores[f"{g}/{c}"][str(lt)] for g, c, lt in flares]
    assert flared and min(flared) > 10 * max(clean)
    # flare_policy mask: no frame is dropped for its flare; its flare and bulb pixels are flagged instead
    assert report["rejected_frames"] == [] and report["broken_frames"] == []
    flagged = {f["frame"] for f in report["flare"]["flagged_frames"]}
    assert flagged and flagged <= {f"{g}/{c}/{lt:03d}" for g, c, lt in any_nuisance}


def test_a_frame_with_a_bulb_in_view_stays_in_the_split_with_its_flare_flagged(
    tiny_run, tiny_capture: Path
) -> None:
    """Issue 53: frames whose bulb is in view are kept (train and test), their bulb and flare pixels are in the
    frame's flare mask, and no frame without its light in view scores or gets a mask."""
    from lightstage.dataset.split import SplitConfig, run_split
    from lightstage.records.processed import read_flare_mask, read_mask
    from lightstage.records.split import load_split

    work, _ = tiny_run
    report = json.loads(work.report("preprocess").read_text())
    nuisances = json.loads((tiny_capture / "ground_truth" / "nuisances.json").read_text())
    bulbs = {f"{b['group']}/{b['camera']}/{b['light']:03d}" for b in nuisances["bulbs_in_view"]}
    in_view = bulbs | {f"{f['group']}/{f['camera']}/{f['light']:03d}" for f in nuisances["flares"]}
    assert bulbs and report["flare"]["policy"] == "mask" and report["rejected_frames"] == []
    flagged = {f["frame"]: f["fraction"] for f in report["flare"]["flagged_frames"]}
    assert bulbs <= set(flagged) <= in_view
    for view, scores in report["flare"]["scores"].items():
        for lt, score in scores.items():
            frame = f"{view}/{int(lt):03d}"
            if frame not in in_view:
                assert score == 0.0 and not work.flare_mask(FrameId(*view.split("/"), int(lt))).exists()
    for name in sorted(bulbs):
        frame = FrameId(*name.split("/")[:2], int(name.split("/")[2]))
        _, sat = read_processed(work.frame(frame))
        flare = read_flare_mask(work.flare_mask(frame), sat.shape)
        bulb = sat & ~read_mask(work.mask(ViewId(frame.group, frame.camera)))
        assert bulb.any() and flare[bulb].all(), name  # the clipped bulb is flagged
        assert 0 < flare.mean() == pytest.approx(flagged[name], abs=1e-4)
    protocol = {"cameras": {"test": ["cam00"], "train": "rest"}, "lights": {"train": "rest", "test": [6]}}
    summary = run_split(work, SplitConfig(protocol), progress=False)
    assert summary["counts"]["train_excluded"] == summary["counts"]["test_excluded"] == 0
    split = load_split(work.split)
    kept = {str(f) for f in split.train.frames()} | {str(f) for f in split.test.frames()}
    assert bulbs <= kept  # the back-lit frames with a bulb in view are test frames
    protocol = {"lights": {"train": [lt for lt in range(12) if lt != 0], "test": [0]}}
    run_split(work, SplitConfig(protocol), progress=False)
    train = {str(f) for f in load_split(work.split).train.frames()}
    cameras = {f.split("/")[1] for f in train}
    on_train_cameras = {f for f in flagged if f.split("/")[1] in cameras}
    assert on_train_cameras and on_train_cameras <= train  # ... and training frames, their flare flagged
    _flagged_rays_carry_no_loss(work, tiny_capture, flagged)


def _flagged_rays_carry_no_loss(work: WorkDir, capture: Path, flagged: dict[str, float]) -> None:
    """Shard the split above (true calibration): rays of flagged frames carry the flare bit exactly on their flare
    mask within the object mask, and a prediction wrong only on those rays costs no photometric loss."""
    import torch

    from lightstage.dataset.loader import RayShardDataset
    from lightstage.dataset.shard_config import ShardConfig
    from lightstage.dataset.shards import run_shard
    from lightstage.records.processed import read_flare_mask, read_mask
    from lightstage.records.shards import flags_flare, load_manifest
    from lightstage.training.config import LossConfig
    from lightstage.training.losses import total_loss

    work.calibration.parent.mkdir(parents=True, exist_ok=True)
    shutil.copy(capture / "ground_truth" / "geometry.json", work.calibration)
    run_shard(work, ShardConfig(workers=1, rays_per_image=256), progress=False)
    m = load_manifest(work.shards_dir)
    rays = np.concatenate([np.load(work.shards_dir / s["file"]) for s in m["shards"]])
    bit = flags_flare(rays["flags"])
    want = np.zeros(len(rays), bool)
    i, j = rays["pixel"][:, 0].astype(np.int64), rays["pixel"][:, 1].astype(np.int64)
    inside = (i >= 0) & (i < 64) & (j >= 0) & (j < 43)
    for name in flagged:
        g, c, lt = name.split("/")
        if f"{g}/{c}" not in m["views"]:
            continue
        sel = inside & (rays["view"] == m["views"].index(f"{g}/{c}")) & (rays["light"] == int(lt))
        both = read_flare_mask(work.flare_mask(FrameId(g, c, int(lt))), (43, 64)) & read_mask(
            work.mask(ViewId(g, c))
        )
        want[sel] = both[j[sel], i[sel]]
    assert bit.any() and np.array_equal(bit, want)
    batch = RayShardDataset(work.shards_dir, 8).to_tensors(rays)
    pred = batch["rgb"].clone()
    pred[batch["flare"]] = 100.0  # a model that learned the glare
    out = {"rgb": pred, "sigma": torch.zeros(len(rays), 2)}
    assert total_loss(out, batch, LossConfig())[1]["rgb_fine"] == pytest.approx(0.0, abs=1e-9)


def test_bad_frames_are_reported_and_skipped(tiny_capture: Path, tmp_path: Path) -> None:
    cap = _subset_capture(tiny_capture, tmp_path / "cap", groups=1, cameras=2)
    frames = cap / "frames" / "000"
    (frames / "cam00" / "003.exr").unlink()  # missing
    data = (frames / "cam00" / "004.exr").read_bytes()
    (frames / "cam00" / "004.exr").write_bytes(data[: len(data) // 3])  # truncated
    (frames / "cam00" / "005.exr").write_bytes(b"not an exr at all")  # garbage
    write_exr(frames / "cam01" / "001.exr", np.zeros((172, 200, 3), np.float16))  # wrong size
    nan = np.full((172, 256, 3), 0.1, np.float16)
    nan[7, 9, 1] = np.nan
    write_exr(frames / "cam01" / "002.exr", nan)  # non-finite
    work = _work(tmp_path / "work", cap)
    # cam00 loses 3 of 12 frames, cam01 2 (frames with a flare are kept under flare_policy mask)
    summary = run_preprocess(
        work, PreprocessConfig(max_lost_fraction=0.2, max_bad_fraction=0.3), progress=False
    )
    report = json.loads(work.report("preprocess").read_text())
    reasons = {p["frame"]: p["reason"] for p in report["problems"]}
    assert set(reasons) == {
        "000/cam00/003",
        "000/cam00/004",
        "000/cam00/005",
        "000/cam01/001",
        "000/cam01/002",
    }
    assert "not found" in reasons["000/cam00/003"]
    assert "172" in reasons["000/cam01/001"] and "200" in reasons["000/cam01/001"]
    assert "non-finite" in reasons["000/cam01/002"]
    assert report["counts"]["frames_ok"] == 24 - 5 and summary["problems"] == 5
    assert not work.frame(FrameId("000", "cam00", 4)).exists()
    assert work.mask(ViewId("000", "cam00")).is_file() and work.mask(ViewId("000", "cam01")).is_file()
    lost = {v: 0 for v in ("000/cam00", "000/cam01")}
    for frame in list(reasons) + report["rejected_frames"]:
        lost[frame[:9]] += 1
    flagged = {f["view"] for f in report["flagged_views"]}
    assert flagged == {v for v, n in lost.items() if n / 12 > 0.2} and "000/cam00" in flagged
    # a rerun keeps the finished views; fixing a bad frame redoes only its view
    shutil.copy(tiny_capture / "frames" / "000" / "cam01" / "002.exr", frames / "cam01" / "002.exr")
    run_preprocess(work, PreprocessConfig(max_lost_fraction=0.2, max_bad_fraction=0.3), progress=False)
    again = json.loads(work.report("preprocess").read_text())
    assert again["counts"]["views_finished_before"] == 1 and again["counts"]["processed"] == 1
    assert "000/cam01/002" not in {p["frame"] for p in again["problems"]}


def _snapshot(work: WorkDir) -> dict[str, bytes]:
    """Every output file except the report (timings) and the previews book."""
    out = {}
    for p in sorted(work.preprocess_dir.rglob("*")):
        if not p.is_file():
            continue
        if p.suffix == ".npz":  # zip members carry timestamps: compare the arrays
            with np.load(p) as d:
                out[str(p.relative_to(work.root))] = b"".join(k.encode() + d[k].tobytes() for k in d.files)
        elif p.name != "view.json":
            out[str(p.relative_to(work.root))] = p.read_bytes()
        else:
            d = json.loads(p.read_text())
            d.pop("seconds"), d.pop("chunks")
            out[str(p.relative_to(work.root))] = json.dumps(d, sort_keys=True).encode()
    return out


@pytest.mark.slow
def test_sfm_image_factor_and_light_spread() -> None:
    from lightstage.preprocess.sfm_image import sfm_image_factor, spread_lights
    from lightstage.workdir import DOWNSCALE

    assert sfm_image_factor(768, 512, 2048) == 1  # small: raw
    assert sfm_image_factor(8192, 5464, 2048) == DOWNSCALE  # paper: the processed frames
    assert sfm_image_factor(4096, 2732, 2048) == 2
    assert sfm_image_factor(768, 512, 0) == DOWNSCALE  # 0: always the processed frames
    assert sfm_image_factor(770, 514, 500) == 2  # 3 does not divide 770
    assert spread_lights(list(range(32)), 4) == [0, 10, 21, 31]
    assert spread_lights([5, 1, 3], 8) == [1, 3, 5]


def _trimmed_mean(frames: list[np.ndarray]) -> np.ndarray:
    stack = np.stack(frames).astype(np.float64)
    return (stack.sum(0) - stack.max(0)) / (len(frames) - 1)


def test_sfm_image_of_a_view_is_the_trimmed_mean_of_raw_frames(tiny_run, tiny_capture: Path) -> None:
    """tiny's raw 256x172 fits the 2048 cap: the SfM image is at raw resolution, from raw frames, with the view's
    rejected and flared frames left out; sfm.png and sfm_mask.png match it and sfm_images.json says so."""
    import cv2

    from lightstage.capture.layout import open_capture
    from lightstage.frames import read_exr
    from lightstage.preprocess.sfm_image import spread_lights

    work, _ = tiny_run
    cap = open_capture(tiny_capture)
    info = json.loads(work.sfm_info.read_text())
    assert info["factor"] == 1 and info["size"] == [256, 172] and info["exposure"] > 0
    assert info["lights"] == min(12, PreprocessConfig().sfm_lights)  # tiny has 12 lights
    report = json.loads(work.report("preprocess").read_text())
    # left out of the SfM image: rejected frames and frames with a flare or bulb in view
    rejected = set(report["rejected_frames"]) | {f["frame"] for f in report["flare"]["flagged_frames"]}
    for view in (ViewId("040", "cam01"), *[ViewId(*f.split("/")[:2]) for f in sorted(rejected)[:2]]):
        record = json.loads((work.view_dir(view) / "view.json").read_text())
        count = PreprocessConfig().sfm_lights  # what tiny_run used
        chosen = [lt for lt in spread_lights(list(range(12)), count) if f"{view}/{lt:03d}" not in rejected]
        assert record["sfm_lights"] == chosen
        raw = [read_exr(cap.frame_path(FrameId(view.group, view.camera, lt))) for lt in chosen]
        hdr = read_exr(work.sfm_hdr(view)).astype(np.float32)
        np.testing.assert_allclose(hdr, _trimmed_mean(raw), rtol=2e-3, atol=1e-6)  # stored as half
        png = cv2.imread(str(work.sfm_image(view)), cv2.IMREAD_UNCHANGED)
        mask = cv2.imread(str(work.sfm_mask(view)), cv2.IMREAD_UNCHANGED)
        assert png.shape == (172, 256, 3) and png.dtype == np.uint8 and png.max() > 100
        small_mask = cv2.imread(str(work.mask(view)), cv2.IMREAD_UNCHANGED)
        np.testing.assert_array_equal(mask[::4, ::4], small_mask)  # nearest-neighbour upsampling


def test_sfm_image_at_processed_resolution(tiny_capture: Path, tmp_path: Path) -> None:
    from lightstage.frames import read_exr

    cap = _subset_capture(tiny_capture, tmp_path / "cap", groups=1, cameras=1)
    work = _work(tmp_path / "work", cap)
    run_preprocess(work, PreprocessConfig(sfm_max_side=0, sfm_lights=3, sfm_trim=False), progress=False)
    view = ViewId("000", "cam00")
    record = json.loads((work.view_dir(view) / "view.json").read_text())
    left_out = set(record["rejected"]) | {int(lt) for lt in record["flared"]}
    assert record["sfm_lights"] == [lt for lt in (0, 6, 11) if lt not in left_out]
    assert len(record["sfm_lights"]) >= 2
    frames = [read_processed(work.frame(FrameId("000", "cam00", lt)))[0] for lt in record["sfm_lights"]]
    hdr = read_exr(work.sfm_hdr(view)).astype(np.float32)
    np.testing.assert_allclose(hdr, np.mean(frames, axis=0), rtol=2e-3, atol=1e-6)
    info = json.loads(work.sfm_info.read_text())
    assert info["size"] == [64, 43] and info["lights"] == 3


def test_killed_run_resumes_with_identical_outputs(tiny_capture: Path, tmp_path: Path) -> None:
    cap = _subset_capture(tiny_capture, tmp_path / "cap", groups=2, cameras=2)
    config = tmp_path / "pp.yaml"
    config.write_text("chunk_lights: 4\n")
    cmd = [sys.executable, "-m", "lightstage.pipelines.cli", "preprocess", str(cap), "--config", str(config)]
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    killed = WorkDir.at(tmp_path / "killed")
    proc = subprocess.Popen([*cmd, "--work", str(killed.root), "--quiet"], env=env)
    deadline = time.time() + 120
    try:
        while time.time() < deadline and proc.poll() is None:
            done = list((killed.preprocess_dir / "frames").rglob("[0-9]*.exr"))
            if len(done) >= 20:  # mid-way: some views finished, one partly
                break
            time.sleep(0.02)
        assert proc.poll() is None, "the run finished before it could be killed"
        os.kill(proc.pid, signal.SIGKILL)
    finally:
        proc.wait()
    assert not killed.report("preprocess").exists()
    n_before = len(list((killed.preprocess_dir / "frames").rglob("[0-9]*.exr")))
    assert 0 < n_before < 48
    subprocess.run([*cmd, "--work", str(killed.root), "--quiet"], env=env, check=True, capture_output=True)
    report = json.loads(killed.report("preprocess").read_text())
    assert report["counts"]["reused"] + report["counts"]["processed"] <= 48
    assert report["counts"]["processed"] <= 48 - n_before + 2  # only unfinished frames were decoded again
    clean = WorkDir.at(tmp_path / "clean")
    subprocess.run([*cmd, "--work", str(clean.root), "--quiet"], env=env, check=True, capture_output=True)
    a, b = _snapshot(killed), _snapshot(clean)
    assert not [k for k in a if Path(k).name.startswith(".")], "temporary files left behind"
    assert sorted(a) == sorted(b)
    assert [k for k in a if a[k] != b[k]] == []


def test_dask_client_gives_the_same_outputs(tiny_capture: Path, tmp_path: Path) -> None:
    from distributed import Client, LocalCluster

    from lightstage.dask_executor import DaskExecutor

    cap = _subset_capture(tiny_capture, tmp_path / "cap", groups=1, cameras=2)
    local = _work(tmp_path / "local", cap)
    run_preprocess(local, PreprocessConfig(chunk_lights=5), progress=False)
    dist = _work(tmp_path / "dask", cap)
    with LocalCluster(n_workers=1, threads_per_worker=2, processes=False, dashboard_address=None) as lc:
        with Client(lc) as client:
            summary = run_preprocess(
                dist, PreprocessConfig(chunk_lights=5), DaskExecutor(client), progress=False
            )
    assert summary["counts"]["processed"] == 24 and summary["errors"] == 0
    a, b = _snapshot(local), _snapshot(dist)
    assert sorted(a) == sorted(b) and [k for k in a if a[k] != b[k]] == []
