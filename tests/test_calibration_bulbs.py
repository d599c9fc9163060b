"""Bulbs seen directly by cameras: sub-pixel disc centres in 4x area-downscaled frames, partly hidden and cut
discs rejected, groups combined, sightings found on a simulated capture (also when the segmentation swallows the
bulb), and the rays turned into light positions and gauge constraints."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from lightstage.calibration.bulbs import (
    BulbDisc,
    BulbSighting,
    bulb_rays,
    combine_discs,
    detect_bulb,
    find_bulbs,
)
from lightstage.calibration.light_rays import LightRay, gauge_points, locate_lights, ray_misfit
from lightstage.cameras import look_at
from lightstage.capture.layout import open_capture
from lightstage.ids import ViewId
from lightstage.records.calibration import Calibration
from lightstage.workdir import DOWNSCALE, WorkDir

CLIP = 4.4


def _frame(centre_raw, radius_raw, size=(96, 64), background=0.01, hidden=None):
    """Processed (4x area mean) RGB + saturation flags of a raw frame showing a clipped disc (raw pixel centres
    inside the disc are clipped), on a dim background. `hidden`: raw-resolution bool map of an object in front
    (dim, not clipped)."""
    w, h = size
    rows, cols = np.mgrid[0 : 4 * h, 0 : 4 * w]
    disc = (cols + 0.5 - centre_raw[0]) ** 2 + (rows + 0.5 - centre_raw[1]) ** 2 <= radius_raw**2
    if hidden is not None:
        disc &= ~hidden
    raw = np.where(disc, CLIP, background).astype(np.float32)
    if hidden is not None:
        raw[hidden] = 0.3
    rgb = cv2.resize(np.repeat(raw[..., None], 3, axis=-1), (w, h), interpolation=cv2.INTER_AREA)
    sat = disc.reshape(h, 4, w, 4).any(axis=(1, 3))
    return rgb, sat


def test_detect_bulb_centre_is_subpixel():
    mask = np.zeros((64, 96), bool)
    mask[20:50, 10:30] = True  # the object, away from the bulb
    for cx, cy in [(250.3, 100.7), (261.0, 141.25), (300.8, 90.1)]:
        rgb, sat = _frame((cx, cy), 15.0)
        disc = detect_bulb(rgb, sat, mask, CLIP)
        # Processed coordinates are raw / 4 under the pixel-centre convention.
        assert abs(disc.u - cx / 4) < 0.05 and abs(disc.v - cy / 4) < 0.05
        assert abs(disc.area - np.pi * (15.0 / 4) ** 2) < 2.0
        assert disc.roundness > 0.97 and not disc.touches_mask


def test_detect_bulb_rejects_partly_hidden_and_cut_bulbs():
    empty = np.zeros((64, 96), bool)
    # A whole disc next to the object's mask is returned, flagged (the segmentation may have swallowed it).
    rgb, sat = _frame((250.3, 100.7), 15.0)
    mask = empty.copy()
    mask[:, 66:] = True
    disc = detect_bulb(rgb, sat, mask, CLIP)
    assert disc is not None and disc.touches_mask
    # The same disc with a sliver (~3.5% of its area) hidden behind the object: not round (0.89), rejected.
    rows, cols = np.mgrid[0:256, 0:384]
    hidden = cols >= 263
    rgb, sat = _frame((250.3, 100.7), 15.0, hidden=hidden)
    assert detect_bulb(rgb, sat, hidden.reshape(64, 4, 96, 4).any(axis=(1, 3)), CLIP) is None
    assert detect_bulb(rgb, sat, empty, CLIP) is None  # even when the mask misses the object
    rgb, sat = _frame((4.0, 100.0), 15.0)  # cut by the image border
    assert detect_bulb(rgb, sat, empty, CLIP) is None
    rgb, sat = _frame((250.0, 100.0), 0.0)  # nothing clipped
    assert detect_bulb(rgb, sat, empty, CLIP) is None


def test_detect_bulb_keeps_whole_discs_that_reach_the_border():
    """A disc whose raw pixels end in the last raw row touches the processed image's last row but is whole:
    kept, unbiased. Cut by 2 raw rows (~2.5% of its area), it is no longer round: rejected."""
    empty = np.zeros((64, 96), bool)
    rgb, sat = _frame((250.3, 256 - 15.2), 15.0)
    assert sat[-1].any()
    disc = detect_bulb(rgb, sat, empty, CLIP)
    assert disc is not None and abs(disc.v - (256 - 15.2) / 4) < 0.02
    rgb, sat = _frame((250.3, 256 - 13.0), 15.0)
    assert detect_bulb(rgb, sat, empty, CLIP) is None


def test_detect_bulb_takes_the_disc_near_the_expected_position():
    a, b = _frame((100.3, 100.7), 15.0), _frame((300.2, 150.9), 11.0)
    rgb, sat = np.maximum(a[0], b[0]), a[1] | b[1]
    empty = np.zeros((64, 96), bool)
    assert abs(detect_bulb(rgb, sat, empty, CLIP).u - 100.3 / 4) < 0.05  # the largest without `near`
    assert abs(detect_bulb(rgb, sat, empty, CLIP, near=(74.0, 38.0)).u - 300.2 / 4) < 0.05
    assert detect_bulb(rgb, sat, empty, CLIP, near=(74.0, 5.0), max_offset_px=20.0) is None


def test_combine_discs_prefers_groups_clear_of_the_mask():
    d = BulbDisc
    discs = {
        "000": d(10.0, 20.0, 50.0, 0.99, False),
        "040": d(10.2, 20.0, 50.2, 0.99, True),
        "080": d(12.0, 20.0, 40.0, 0.96, False),  # smaller: partly hidden
        "120": d(10.1, 20.1, 49.9, 0.98, False),
    }
    s = combine_discs(3, "cam01", discs)
    assert s.groups == ["000", "120"] and not s.touching_mask
    assert s.uv == pytest.approx((10.05, 20.05)) and (s.light, s.camera) == (3, "cam01")
    # Only mask-touching discs: accepted when enough groups (different silhouettes) agree.
    touching = {g: d(10.0, 20.0, 50.0, 0.99, True) for g in ("000", "040", "080")}
    assert combine_discs(3, "cam01", touching).touching_mask
    assert combine_discs(3, "cam01", dict(list(touching.items())[:2])) is None
    # ... with the same centre: a clipped highlight moving with the object from group to group is no bulb.
    moving = {g: d(10.0 + i, 20.0, 50.0, 0.99, True) for i, g in enumerate(("000", "040", "080", "120"))}
    assert combine_discs(3, "cam01", moving) is None
    assert combine_discs(3, "cam01", {}) is None


def _ring_rig(n: int = 6):
    """n cameras on a 1.1 m ring at z = 0.2 looking at the origin; processed K."""
    K = np.array([[500.0, 0, 96], [0, 500.0, 64], [0, 0, 1]])
    cams = {}
    for i in range(n):
        a = 2 * np.pi * i / n
        cams[f"cam{i:02d}"] = look_at(np.array([1.1 * np.cos(a), 1.1 * np.sin(a), 0.2]), np.zeros(3))
    return cams, {c: K for c in cams}


def _sight(light: int, cam: str, p: np.ndarray, cams, Ks) -> BulbSighting:
    R, t = cams[cam]
    pc = R @ p + t
    uv = (Ks[cam] @ pc)[:2] / pc[2]
    return BulbSighting(light, cam, (float(uv[0]), float(uv[1])), ["000"])


def test_locate_lights_triangulates_and_moves_single_sightings_onto_their_ray():
    cams, Ks = _ring_rig()
    nominal = np.array([[-1.45, 0.1, 0.4], [-1.4, -0.3, 0.5], [0.3, 1.4, 0.2]])
    true = nominal + np.array([[0.004, -0.003, 0.002], [-0.002, 0.003, 0.004], [0.0, 0.0, 0.0]])
    sightings = [_sight(0, c, true[0], cams, Ks) for c in ("cam00", "cam01", "cam05")]
    sightings.append(_sight(1, "cam00", true[1], cams, Ks))
    est = locate_lights(bulb_rays(sightings, cams, Ks, pixel_sigma=0.01), nominal, prior_sigma_m=0.003)
    assert np.linalg.norm(est.positions[0] - true[0]) < 1e-4  # triangulated
    # One camera: the light lands on its ray (2 of 3 coordinates observed).
    R, t = cams["cam00"]
    c = -R.T @ t
    d = (true[1] - c) / np.linalg.norm(true[1] - c)
    off = est.positions[1] - c
    assert np.linalg.norm(off - (off @ d) * d) < 1e-4
    np.testing.assert_array_equal(est.positions[2], nominal[2])  # never seen: nominal
    assert sorted(est.sources) == [0, 1] and est.sources[0] == ["bulb cam00", "bulb cam01", "bulb cam05"]
    assert est.shift_mm[0] == pytest.approx(1000 * np.linalg.norm(est.positions[0] - nominal[0]))


def test_locate_lights_drops_a_ray_that_misses_the_others():
    nominal = np.array([[1.5, 0.0, 0.0]])
    true = nominal[0] + [0.002, -0.001, 0.003]
    rays = []
    for i, o in enumerate(np.array([[0, 0, 0], [0, 0.3, 0], [0, 0, 0.3], [0, -0.2, 0.1]], float)):
        d = (true - o) / np.linalg.norm(true - o)
        rays.append(LightRay(0, o, d, 1e-5, f"r{i}"))
    bad_d = (true + [0, 0.03, 0] - rays[0].origin) / np.linalg.norm(true + [0, 0.03, 0])
    rays.append(LightRay(0, np.zeros(3), bad_d, 1e-5, "wrong blob"))
    est = locate_lights(rays, nominal, prior_sigma_m=0.003)
    assert est.rejected_rays == {0: 1} and "wrong blob" not in est.sources[0]
    assert np.linalg.norm(est.positions[0] - true) < 1e-5
    assert ray_misfit(rays[1], true) < 1e-6 and est.sigma_mm[0] < 0.1


def test_gauge_points_weights_follow_the_rays():
    cams, Ks = _ring_rig()
    nominal = np.array([[-1.45, 0.1, 0.4], [-1.4, -0.3, 0.5]])
    true = nominal + 0.002
    sightings = [_sight(0, c, true[0], cams, Ks) for c in ("cam00", "cam01", "cam05")]
    sightings.append(_sight(1, "cam00", true[1], cams, Ks))
    rays = bulb_rays(sightings, cams, Ks, pixel_sigma=0.01)
    lights, pts, nom, L = gauge_points(rays, nominal, mount_sigma_m=0.003)
    assert lights == [0, 1]
    np.testing.assert_allclose(pts[0], true[0], atol=1e-4)
    np.testing.assert_array_equal(nom, nominal)
    # Triangulated: ~isotropic weight 1 / mounting sigma. One ray: nothing along it, 1 / sigma across it.
    np.testing.assert_allclose(L[0], np.eye(3) / 0.003, rtol=0.05, atol=5.0)
    R, t = cams["cam00"]
    d = true[1] - (-R.T @ t)
    d /= np.linalg.norm(d)
    assert np.linalg.norm(L[1] @ d) < 1e-3 * np.linalg.norm(L[1])
    assert np.linalg.svd(L[1], compute_uv=False)[:2] == pytest.approx([1 / 0.003] * 2, rel=0.01)
    assert gauge_points([], nominal)[1].shape == (0, 3)


@pytest.fixture(scope="module")
def tiny_preprocessed(tiny_capture: Path, tmp_path_factory: pytest.TempPathFactory) -> WorkDir:
    from lightstage.preprocess.config import PreprocessConfig
    from lightstage.preprocess.run import run_preprocess

    work = WorkDir.at(tmp_path_factory.mktemp("bulbs") / "work")
    work.root.mkdir()
    work.capture_pointer.write_text(str(tiny_capture))
    run_preprocess(work, PreprocessConfig.from_dict({}), progress=False)
    return work


def test_find_bulbs_on_a_simulated_capture(tiny_capture: Path, tiny_preprocessed: WorkDir):
    """The tiny capture shows light 6's bulb to cam00 (whole in most groups, partly hidden in two): found at its
    true projection; still found when the masks swallow the bulb (as segmentations of bulb + glow do)."""
    import json

    cap = open_capture(tiny_capture)
    stage = cap.stage
    truth = Calibration.load(tiny_capture / "ground_truth" / "geometry.json")
    in_view = json.loads((tiny_capture / "ground_truth" / "nuisances.json").read_text())["bulbs_in_view"]
    assert {(b["light"], b["camera"]) for b in in_view} == {(6, "cam00")}
    nominal_rig = {c.id: (c.R, c.t) for c in stage.cameras}
    found = find_bulbs(tiny_preprocessed, cap, nominal_rig, stage.light_positions_rig())
    assert found.candidates >= 1 and not found.read_errors
    (s,) = found.sightings
    assert (s.light, s.camera) == (6, "cam00") and not s.touching_mask and len(s.groups) >= 3
    vc = truth.views[ViewId("000", "cam00")]
    pc = vc.R @ truth.light_positions["000"][6] + vc.t
    uv = (vc.K_raw @ pc)[:2] / pc[2] / DOWNSCALE
    assert np.hypot(*(np.asarray(s.uv) - uv)) < 0.15

    # Masks that take the bulb as foreground in every group: confirmed by the agreeing groups instead.
    r = 6
    for g in stage.group_names:
        path = tiny_preprocessed.mask(ViewId(g, "cam00"))
        m = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
        cv2.circle(m, (int(uv[0]), int(uv[1])), r, 255, -1)
        cv2.imwrite(str(path), m)
    found = find_bulbs(tiny_preprocessed, cap, nominal_rig, stage.light_positions_rig())
    (s2,) = found.sightings
    assert s2.touching_mask and len(s2.groups) >= 3
    assert np.hypot(*(np.asarray(s2.uv) - uv)) < 0.15
