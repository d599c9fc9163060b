"""The cross-group consistency step (preprocess/consistency.py, camera_task.py): stage structure fixed to the camera
that joined a view's mask leaves it; the turning object, a symmetric object, and captures of 1-2 groups keep theirs;
the step is resumable and can be switched off."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from lightstage.preprocess.config import PreprocessConfig
from lightstage.preprocess.consistency import consistent_masks, noise_fit
from lightstage.preprocess.segment import iou

H, W, G = 48, 64, 9
READ, SHOT = 2e-3, 2e-5  # noise of a view's mean image over 16 frames: var = READ^2 + SHOT * level


def _camera(seed: int = 0, symmetric: bool = False):
    """(means, own masks, true object masks) of one camera's G groups: a textured backdrop with a bright strut,
    fixed to the camera; an ellipse whose texture and outline turn with the group (or, `symmetric`, do not); the
    views' own masks hold the object plus the part of the strut next to it (as on the realistic simulator)."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:H, 0:W].astype(np.float32)
    back = 0.02 * np.exp(0.3 * rng.standard_normal((H, W, 1))) * np.array([0.9, 1.0, 1.2], np.float32)
    strut = np.abs((xx - 0.6 * yy) - 30) < 1.5  # a bar crossing behind the object
    back[strut] *= 3.0
    near = strut & (np.hypot(xx - W / 2, yy - H / 2) < 20)  # the part of it that joined the masks
    means, masks, truths = [], [], []
    for g in range(G):
        ang = 0.0 if symmetric else 2 * np.pi * g / G
        a, b = (10.0, 10.0) if symmetric else (13.0, 8.0)
        u = (xx - W / 2) * np.cos(ang) + (yy - H / 2) * np.sin(ang)
        v = -(xx - W / 2) * np.sin(ang) + (yy - H / 2) * np.cos(ang)
        obj = (u / a) ** 2 + (v / b) ** 2 <= 1
        tex_rng = np.random.default_rng(0 if symmetric else 100 + g)  # the surface under a pixel changes
        colour = (
            0.3 * np.exp(0.4 * tex_rng.standard_normal((H, W, 1))) * np.array([1.0, 0.8, 0.6], np.float32)
        )
        img = np.where(obj[..., None], colour, back)
        img = img + np.sqrt(READ**2 + SHOT * img) * rng.standard_normal(img.shape)
        means.append(img.astype(np.float32))
        masks.append(obj | near)
        truths.append(obj)
    return np.stack(means), np.stack(masks), np.stack(truths)


def test_noise_fit_recovers_read_and_shot_noise() -> None:
    rng = np.random.default_rng(1)
    level = np.exp(rng.uniform(np.log(1e-3), np.log(0.5), 20000))
    diff = np.sqrt(2 * (READ**2 + SHOT * level)) * rng.standard_normal(level.size)
    a, b = noise_fit(level, diff)
    assert abs(a / READ**2 - 1) < 0.2 and abs(b / SHOT - 1) < 0.1, (a, b)
    assert noise_fit(level[:10], diff[:10]) is None  # too few pixels to measure


def test_structure_fixed_to_the_camera_leaves_the_masks() -> None:
    means, masks, truth = _camera()
    out, info = consistent_masks(means, masks, PreprocessConfig())
    before = [iou(m, t) for m, t in zip(masks, truth, strict=True)]
    after = [iou(m, t) for m, t in zip(out, truth, strict=True)]
    # (what is left of the bar: pixels next to the object, which the turning object covers in other groups)
    assert max(before) < 0.9 and min(after) > 0.96 and np.mean(after) > 0.98, (before, after)
    assert not np.any(truth & ~out)  # nothing of the object was removed
    assert info["matches_needed"] == [4, 2] and min(info["removed"]) > 0
    # the noise measured on the background: the read noise floor within a factor 1.5
    assert all(0.45 < a / READ**2 < 2.2 for a, _ in info["noise"]), info["noise"]


def test_a_symmetric_object_that_looks_fixed_is_not_removed() -> None:
    """A uniform disc centred on the axis is the same in every group: it is as bright as an object and framed
    inside the image, so it is the object, not structure, and keeps its whole mask."""
    means, masks, truth = _camera(symmetric=True)
    out, _ = consistent_masks(means, masks, PreprocessConfig())
    assert all(not np.any(t & ~o) for o, t in zip(out, truth, strict=True))


def test_a_symmetric_part_is_kept_and_fixed_structure_at_the_border_leaves() -> None:
    """structure_parts: a bright fixed part inside the own mask (a symmetric base, smaller than the rest) is the
    object; a fixed part reaching the frame border (a lit floor) and a dim one (a strut) are structure."""
    from lightstage.preprocess.consistency import structure_parts

    loglum = np.full((H, W), -10.0)
    own = np.zeros((H, W), bool)
    own[10:30, 20:44] = True  # the object: 4 stops above the backdrop
    loglum[own] = -6.0
    base = np.zeros((H, W), bool)
    base[24:30, 28:36] = True  # its symmetric base, fixed, as bright as the object
    floor = np.zeros((H, W), bool)
    floor[40:, :] = True  # a lit floor, as bright as the object, leaving the frame
    loglum[floor] = -6.0
    strut = np.zeros((H, W), bool)
    strut[10:14, 20:23] = True  # a dim strut joined the mask
    loglum[strut] = -9.0
    own |= floor
    background = ~own
    border, structure = structure_parts(base | floor | strut, own, loglum, background)
    assert np.array_equal(border, floor) and np.array_equal(structure, floor | strut)


def test_fewer_than_three_groups_or_switched_off_change_nothing() -> None:
    means, masks, _ = _camera()
    for g in (1, 2):
        out, info = consistent_masks(means[:g], masks[:g], PreprocessConfig())
        assert np.array_equal(out, masks[:g]) and "skipped" in info
    cfg = PreprocessConfig(consistency=False)
    assert cfg.view_key() == PreprocessConfig().view_key()  # the switch does not redo the views


def test_camera_step_in_the_stage_is_resumable_and_can_be_switched_off(tmp_path: Path, monkeypatch) -> None:
    """A 3-group realistic tiny capture of one camera: the step runs, writes its marker and the final masks; a
    rerun skips it; a rerun after the marker is lost gives identical outputs; `consistency: false` restores the
    views' own masks."""
    from test_segment_adaptive import _preprocess, _simulate

    from lightstage.frames import write_image
    from lightstage.ids import ViewId
    from lightstage.preprocess.camera_task import camera_marker
    from lightstage.records.processed import read_mask

    cap = _simulate(tmp_path / "cap", monkeypatch, groups="0-2", cameras="0", lights="0-7")
    work = _preprocess(cap, tmp_path / "work")
    marker = camera_marker(work, "cam00")
    assert marker.is_file()
    views = [ViewId(g, "cam00") for g in ("000", "040", "080")]
    recs = [json.loads((work.view_dir(v) / "view.json").read_text()) for v in views]
    assert all(r["consistency"]["groups"] == 3 and "iou_view" in r["consistency"] for r in recs), recs
    first = [read_mask(work.mask(v)) for v in views]
    stamp = marker.stat().st_mtime_ns
    _preprocess(cap, tmp_path / "work")
    assert marker.stat().st_mtime_ns == stamp  # skipped
    # a camera step killed half-way: the marker not written, a mask already rewritten (here: wrongly)
    marker.unlink()
    write_image(work.mask(views[0]), np.zeros(first[0].shape, np.uint8))
    _preprocess(cap, tmp_path / "work")
    assert all(np.array_equal(read_mask(work.mask(v)), m) for v, m in zip(views, first, strict=True))
    _preprocess(cap, tmp_path / "work", consistency=False)
    for v in views:
        with np.load(work.view_dir(v) / "stats.npz") as d:
            assert np.array_equal(read_mask(work.mask(v)), d["mask"])  # the view's own mask
        rec = json.loads((work.view_dir(v) / "view.json").read_text())
        assert rec["consistency"]["removed"] == 0 and "off" in rec["consistency"]["skipped"]


def test_inclusive_mask_takes_a_part_lit_well_in_one_frame_only() -> None:
    """segment_masks: a dark part of the object lit well in a single frame does not stand out in the brightness
    quantiles (the view's own mask) but does in the mean over the stack (the inclusive mask the camera step
    cleans); the view's own mask does not change with it."""
    from lightstage.preprocess.segment import segment, segment_masks
    from lightstage.preprocess.stats import direct_stats

    cutoff, n = 4.4, 16
    rng = np.random.default_rng(0)
    yy, xx = np.mgrid[0:H, 0:W].astype(np.float32)
    body = ((xx - W / 2) / 14) ** 2 + ((yy - 20) / 10) ** 2 <= 1
    foot = (np.abs(xx - W / 2) < 6) & (yy >= 26) & (yy < 38) & ~body  # the dark underside below it
    tint = np.array([0.9, 1.0, 1.2], np.float32)  # the same colour as the backdrop: colour does not help
    back = cutoff * 2.0**-10 * np.exp(0.05 * rng.standard_normal((H, W, 1))) * tint
    frames = []
    for k in range(n):
        img = back.copy()
        img[body] = cutoff * 2.0 ** (-5 if k % 2 else -8) * np.array([1.0, 0.8, 0.6], np.float32)
        img[foot] = cutoff * 2.0 ** (-3 if k == 5 else -11) * tint
        frames.append(img.astype(np.float32))
    st = direct_stats(frames, [np.zeros((H, W), bool)] * n, [0.0] * n, list(range(n)), cutoff)
    own, inclusive, info = segment_masks(st, PreprocessConfig(), cutoff)
    truth = body | foot
    assert not np.any(own & foot) and np.array_equal(own, segment(st, PreprocessConfig(), cutoff))
    assert iou(inclusive, truth) > 0.95 and iou(own, body) > 0.95, (iou(inclusive, truth), iou(own, body))
    assert "mean" in info["quantiles"]  # its measured levels are reported too
