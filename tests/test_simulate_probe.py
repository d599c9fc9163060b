"""The mirror-ball light probe: its contract (probe.yaml), the specular-point solver, the accuracy of the
rendered highlights and silhouettes, and the simulator's probe output."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from lightstage.cameras import PinholeCamera, look_at
from lightstage.capture.layout import open_capture
from lightstage.capture.probe import PROBE_FILE, ProbeInfo, load_probe_info, save_probe_info
from lightstage.errors import LightstageError
from lightstage.exr_header import read_exr_header
from lightstage.frames import read_exr
from lightstage.rig import group_transform
from lightstage.simulator.probe import ProbeSettings
from lightstage.simulator.probe_optics import (
    ball_centre_rig,
    probe_base_images,
    render_probe_olat,
    specular_point,
)
from lightstage.simulator.render import add_noise_and_clip
from lightstage.simulator.scene import default_scene
from lightstage.simulator.simulate import load_truth, simulate_capture


# ---- the contract ----------------------------------------------------------------------------------------------
def test_probe_info_round_trip_and_errors(tmp_path: Path) -> None:
    assert load_probe_info(tmp_path) is None
    info = ProbeInfo(0.0508, ("000", "120", "240"), notes={"ball": "4 inch chrome", "n": 3})
    path = save_probe_info(info, tmp_path)
    assert path == tmp_path / PROBE_FILE and path.is_file()
    back = load_probe_info(tmp_path)
    assert back == info
    assert back.frame(tmp_path, "120", "cam03", 7) == tmp_path / "probe/120/cam03/007.exr"
    assert back.ambient(tmp_path, "240", "cam00") == tmp_path / "probe/240/cam00/ambient.exr"
    custom = ProbeInfo(
        0.03, ("a",), "ball/{position}-{camera}-{light}.exr", "ball/{position}-{camera}-amb.exr"
    )
    save_probe_info(custom, tmp_path)
    assert load_probe_info(tmp_path) == custom

    bad = {
        "- 1\n- 2\n": "mapping",
        "radius_m: -0.05\npositions: ['000']\n": "radius_m",
        "radius_m: 0\npositions: ['000']\n": "radius_m",
        "positions: ['000']\n": "radius_m",
        "radius_m: 0.05\npositions: []\n": "positions",
        "radius_m: 0.05\npositions: [000]\n": r"positions\[0\]",
        "radius_m: 0.05\npositions: ['a', 'a']\n": "duplicate",
        "radius_m: 0.05\npositions: ['a']\npath_template: 'probe/{position}/{camera}.exr'\n": "light",
        "radius_m: 0.05\npositions: ['a']\npath_template: 'probe/{group}/{camera}/{light}.exr'\n": "path_template",
        "radius_m: 0.05\npositions: ['a']\nambient_template: 'probe/{camera}.exr'\n": "ambient_template",
        "radius_m: 0.05\npositions: ['a']\nambient_template: 'probe/{position}/{camera}/000.exr'\n": "collides",
        "radius_m: 0.05\npositions: ['a']\nnotes: [1]\n": "notes",
        "radius_m: [0.05\n": "invalid YAML",
    }
    for text, what in bad.items():
        (tmp_path / PROBE_FILE).write_text(text)
        with pytest.raises(LightstageError, match=what) as e:
            load_probe_info(tmp_path)
        assert "probe.yaml" in str(e.value), text
    with pytest.raises(LightstageError, match="radius_m"):
        save_probe_info(ProbeInfo(-1.0, ("000",)), tmp_path / "other")
    assert not (tmp_path / "other" / PROBE_FILE).exists()


# ---- the specular point ----------------------------------------------------------------------------------------
def _angle(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angles between rows of a and b, accurate at every angle (atan2 of |a x b| and a.b)."""
    return np.arctan2(np.linalg.norm(np.cross(a, b), axis=-1), np.einsum("ij,ij->i", a, b))


def test_specular_point_bisects_camera_and_light() -> None:
    rng = np.random.default_rng(1)
    checked = 0
    for _ in range(200):
        c = rng.uniform(-1, 1, 3)
        r = rng.uniform(0.01, 0.5)

        def outside(n: int, c: np.ndarray = c, r: float = r) -> np.ndarray:
            d = rng.standard_normal((n, 3))
            d /= np.linalg.norm(d, axis=-1, keepdims=True)
            return c + d * r * rng.uniform(1.05, 40.0, (n, 1))

        C = outside(1)[0]
        P = outside(8)
        x, valid = specular_point(c, r, C, P)
        assert valid.mean() > 0.5
        np.testing.assert_allclose(np.linalg.norm(x - c, axis=-1), r, rtol=1e-12)
        x, P = x[valid], P[valid]
        n = (x - c) / r
        to_cam, to_light = C - x, P - x
        a_cam, a_light = _angle(n, to_cam), _angle(n, to_light)
        assert np.abs(a_cam - a_light).max() < 1e-9
        assert (a_cam < np.pi / 2).all() and (a_light < np.pi / 2).all()
        # coplanar with the normal (the reflected ray goes to the light, not just at the same angle)
        bis = to_cam / np.linalg.norm(to_cam, axis=-1, keepdims=True)
        bis = bis + to_light / np.linalg.norm(to_light, axis=-1, keepdims=True)
        assert np.abs(_angle(n, bis)).max() < 1e-9
        checked += len(x)
    assert checked > 1000
    # degenerate: light in front on the camera line reflects at the near pole; right behind the ball: none
    c, C = np.zeros(3), np.array([0.0, 0.0, 2.0])
    x, valid = specular_point(c, 0.1, C, np.array([[0.0, 0.0, 3.0], [0.0, 0.0, -3.0]]))
    np.testing.assert_allclose(x[0], [0.0, 0.0, 0.1], atol=1e-15)
    assert valid.tolist() == [True, False]


# ---- rendering accuracy ----------------------------------------------------------------------------------------
def _view() -> PinholeCamera:
    """A tiny-like view of the default ball: 256 x 172, focal 2.7 x width, 1.1 m away, slightly off-centre."""
    w, h = 256, 172
    f = 2.7 * w
    K = np.array([[f, 0, w / 2], [0, f, h / 2], [0, 0, 1.0]])
    R, t = look_at(np.array([0.93, 0.31, 0.52]), np.array([0.01, 0.005, 0.003]))
    return PinholeCamera(K, R, t, w, h)


def _lights(n: int) -> np.ndarray:
    rng = np.random.default_rng(3)
    d = rng.standard_normal((n, 3))
    d[:, 2] = np.abs(d[:, 2]) * 0.8 - 0.2
    return 1.5 * d / np.linalg.norm(d, axis=-1, keepdims=True)


def test_highlight_centroid_is_the_true_specular_point() -> None:
    cam, scene, s = _view(), default_scene(), ProbeSettings()
    _, base, _ = probe_base_images(cam, scene, s)
    rng = np.random.default_rng(4)
    errs, noisy_errs = [], []
    for k, p in enumerate(_lights(40)):
        img, hl, bulb = render_probe_olat(cam, p, scene, s, 1.5, base, light_id=k)
        x, valid = specular_point(np.asarray(s.centre_world), s.radius_m, cam.center, p[None])
        if not valid[0]:
            continue
        pc = cam.R @ x[0] + cam.t
        uv = (cam.K @ pc)[:2] / pc[2]
        np.testing.assert_allclose(hl.uv, uv, atol=1e-9)
        i, j = int(np.floor(uv[0])), int(np.floor(uv[1]))
        if not (6 <= i < cam.width - 6 and 6 <= j < cam.height - 6):
            continue
        win = (slice(j - 5, j + 6), slice(i - 5, i + 6))
        if bulb is not None and ((np.abs(bulb[0] - j) <= 8) & (np.abs(bulb[1] - i) <= 8)).any():
            continue
        assert 1.0 < img[j, i].max() < 3.0  # the exposure keeps highlights well below the 4.4019 cutoff
        for frame, out in (
            (img, errs),
            (add_noise_and_clip(img, scene, 4.4019, rng.standard_normal(img.size, np.float32)), noisy_errs),
        ):
            sig = (frame.astype(np.float32) - base)[win].mean(-1).astype(np.float64)
            jj, ii = np.mgrid[win]
            cu = (sig * (ii + 0.5)).sum() / sig.sum()
            cv = (sig * (jj + 0.5)).sum() / sig.sum()
            out.append(np.hypot(cu - uv[0], cv - uv[1]))
    assert len(errs) >= 20
    assert max(errs) < 1e-3, max(errs)
    assert max(noisy_errs) < 0.02, max(noisy_errs)


def _outline_u(cam: PinholeCamera, centre: np.ndarray, r: float, v: float) -> tuple[float, float] | None:
    """Columns where the row v crosses the projected outline of the sphere (the tangent cone d.a = cos asin(r/D))."""
    C = cam.center
    a = centre - C
    D = np.linalg.norm(a)
    ac = cam.R @ (a / D)
    cos2 = 1.0 - (r / D) ** 2
    fx, fy, cx, cy = cam.K[0, 0], cam.K[1, 1], cam.K[0, 2], cam.K[1, 2]
    w0 = np.array([-cx / fx, (v - cy) / fy, 1.0])
    e = np.array([1.0 / fx, 0.0, 0.0])
    # (w0.a + u e.a)^2 = cos2 (|w0|^2 + 2 u w0.e + u^2 |e|^2)
    A = (e @ ac) ** 2 - cos2 * (e @ e)
    B = 2 * (w0 @ ac) * (e @ ac) - 2 * cos2 * (w0 @ e)
    Cq = (w0 @ ac) ** 2 - cos2 * (w0 @ w0)
    disc = B * B - 4 * A * Cq
    if disc <= 0:
        return None
    roots = sorted([(-B - np.sqrt(disc)) / (2 * A), (-B + np.sqrt(disc)) / (2 * A)])
    return roots[0], roots[1]


def _row_crossings(row: np.ndarray, level: float) -> tuple[float, float]:
    """First rising and last falling crossing of `level`, linear between pixel centres."""
    above = row >= level
    i0 = int(np.argmax(above))
    i1 = len(row) - 1 - int(np.argmax(above[::-1]))
    left = i0 - 1 + 0.5 + (level - row[i0 - 1]) / (row[i0] - row[i0 - 1])
    right = i1 + 0.5 + (row[i1] - level) / (row[i1] - row[i1 + 1])
    return left, right


def test_ambient_silhouette_is_the_projected_sphere() -> None:
    cam, scene, s = _view(), default_scene(), ProbeSettings()
    _, _, amb = probe_base_images(cam, scene, s)
    noisy = add_noise_and_clip(
        amb, scene, 4.4019, np.random.default_rng(5).standard_normal(amb.size, np.float32)
    )
    c = np.asarray(s.centre_world)
    radius_px = cam.K[0, 0] * s.radius_m / np.linalg.norm(c - cam.center)
    inside = s.reflectance * s.ambient_radiance
    for img, tol in ((amb, 0.03), (noisy.astype(np.float32), 0.05)):
        g = img[..., 1].astype(np.float64)
        level = 0.5 * (inside + np.median(g[:10]))
        assert np.median(g[g > level]) == pytest.approx(inside, rel=0.02)
        errs = []
        for j in range(cam.height):
            ends = _outline_u(cam, c, s.radius_m, j + 0.5)
            if ends is None or ends[1] - ends[0] < 2 * 0.7 * radius_px:  # steep parts of the outline only
                continue
            left, right = _row_crossings(g[j], level)
            errs += [left - ends[0], right - ends[1]]
        errs = np.asarray(errs)
        assert len(errs) > 60
        assert np.abs(errs).mean() < tol, np.abs(errs).mean()
        assert abs(errs.mean()) < tol  # no bias (in or out)
        assert np.abs(errs).max() < 0.2


# ---- the simulator's output -------------------------------------------------------------------------------------
def test_simulated_probe_files_truth_and_determinism(tmp_path: Path, tree_hash) -> None:
    from lightstage.capture.validate import validate_capture

    sel = {"groups": "000,120", "cameras": "0,3", "lights": "0-8:4"}
    a = simulate_capture(tmp_path / "a", "tiny", seed=5, workers=1, progress=False, **sel)
    b = simulate_capture(tmp_path / "b", "tiny", seed=5, workers=2, progress=False, **sel)
    assert tree_hash(a / "probe") == tree_hash(b / "probe")
    assert (a / "ground_truth/probe.json").read_bytes() == (b / "ground_truth/probe.json").read_bytes()

    cap = open_capture(a)
    info = load_probe_info(a)
    assert info is not None and info.positions == ("000", "120")
    expected = set()
    for pos in info.positions:
        for cam in cap.stage.camera_ids:
            expected.add(info.ambient(a, pos, cam))
            for lt in cap.stage.lights:
                expected.add(info.frame(a, pos, cam, lt.index))
    assert len(expected) == 2 * 2 * (3 + 1)
    assert expected == {p for p in (a / "probe").rglob("*.exr")}
    for p in expected:
        h = read_exr_header(p)
        assert (h.width, h.height) == (cap.stage.width, cap.stage.height)
        assert h.dtype == "half" and "piz" in h.compression.lower()

    gt = json.loads((a / "ground_truth/probe.json").read_text())
    truth = load_truth(a)
    assert gt["radius_m"] == info.radius_m
    c = np.asarray(gt["ball_centre_world"])
    for pos in info.positions:
        Rg, tg = group_transform(truth.yaws_deg[pos], truth.axis)
        rig = np.asarray(gt["positions"][pos]["ball_centre_rig"])
        np.testing.assert_allclose(Rg @ rig + tg, c, atol=1e-12)
        np.testing.assert_allclose(ball_centre_rig(c, truth.yaws_deg[pos], truth.axis), rig, atol=1e-15)
    assert gt["peak_highlight_pixel"] < cap.stage.saturation
    # the written (noisy, half) frames have their highlight where the ground truth says
    hls = [h for h in gt["highlights"] if h["visible"]]
    assert len(hls) == len(gt["highlights"]) == 2 * 2 * 3
    bulbs = {(r["position"], r["camera"], r["light"]) for r in gt["bulbs_in_view"]}
    checked = 0
    for h in hls:
        if (h["position"], h["camera"], h["light"]) in bulbs:
            continue
        img = read_exr(info.frame(a, h["position"], h["camera"], h["light"])).astype(np.float64).mean(-1)
        u, v = h["uv"]
        i, j = int(np.floor(u)), int(np.floor(v))
        win = (slice(j - 5, j + 6), slice(i - 5, i + 6))
        sig = img[win] - np.median(img[j - 12 : j + 13, i - 12 : i + 13])
        jj, ii = np.mgrid[win]
        assert (
            np.hypot((sig * (ii + 0.5)).sum() / sig.sum() - u, (sig * (jj + 0.5)).sum() / sig.sum() - v)
            < 0.05
        )
        checked += 1
    assert checked >= 6
    amb = read_exr(info.ambient(a, "120", cap.stage.camera_ids[0])).astype(np.float32)
    assert (amb[..., 1] > 0.25).sum() > 1000  # the ball's disc (~31 px radius)

    assert validate_capture(a, progress=False).ok


def test_tiny_capture_has_a_probe(tiny_capture: Path) -> None:
    info = load_probe_info(tiny_capture)
    assert info is not None and info.positions == ("000", "120", "240")
    cap = open_capture(tiny_capture)
    for pos in info.positions:
        for cam in cap.stage.camera_ids:
            assert info.ambient(tiny_capture, pos, cam).is_file()
            assert all(info.frame(tiny_capture, pos, cam, lt.index).is_file() for lt in cap.stage.lights)
    gt = json.loads((tiny_capture / "ground_truth/probe.json").read_text())
    assert set(gt["positions"]) == set(info.positions)
    assert len(gt["highlights"]) == 3 * len(cap.stage.cameras) * len(cap.stage.lights)
