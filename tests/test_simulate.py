"""The simulator: layout and contract of its captures, determinism, physical sanity of the renders, ground truth."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from lightstage.capture.layout import open_capture
from lightstage.errors import LightstageError
from lightstage.exr_header import read_exr_header
from lightstage.frames import read_exr, read_image
from lightstage.ids import FrameId
from lightstage.simulator.render import saturation_value
from lightstage.simulator.scene import Ellipsoid
from lightstage.simulator.simulate import SIM_PRESETS, load_scene, load_truth, render_clean, simulate_capture


def _mask(root: Path, group: str, camera: str) -> np.ndarray:
    m = read_image(root / "ground_truth" / "masks" / group / f"{camera}.png")
    return m[..., 0] > 0.5


def test_tiny_capture_contract(tiny_capture: Path) -> None:
    cap = open_capture(tiny_capture)
    p = SIM_PRESETS["tiny"]
    assert (len(cap.stage.groups), len(cap.stage.cameras), len(cap.stage.lights)) == (
        p.num_groups,
        p.num_cameras,
        p.num_lights,
    )
    assert cap.stage.width % 4 == 0 and cap.stage.height % 4 == 0
    frames = list(cap.frames())
    assert all(cap.frame_path(f).is_file() for f in frames)
    h = read_exr_header(cap.frame_path(frames[0]))
    assert (h.width, h.height) == (cap.stage.width, cap.stage.height)
    assert h.dtype == "half" and "piz" in h.compression.lower()
    gt = tiny_capture / "ground_truth"
    for name in ("geometry.json", "scene.json", "clean.json", "nuisances.json"):
        assert (gt / name).is_file()
    for v in cap.views():
        assert (gt / "masks" / v.group / f"{v.camera}.png").is_file()
    clean = json.loads((gt / "clean.json").read_text())
    assert clean["lights"]
    for v in cap.views():
        for lt in clean["lights"]:
            assert (gt / "clean" / v.group / v.camera / f"{lt:03d}.exr").is_file()
    assert (tiny_capture / "contact_sheet.png").stat().st_size > 1000


def test_pixels_finite_nonnegative_and_clipped(tiny_capture: Path) -> None:
    cap = open_capture(tiny_capture)
    sat = float(saturation_value(cap.stage.saturation))
    for f in cap.frames():
        img = read_exr(cap.frame_path(f)).astype(np.float32)
        assert np.isfinite(img).all(), f
        assert img.min() >= 0.0, f
        assert img.max() <= sat, f


def test_nominal_stage_differs_from_truth(tiny_capture: Path) -> None:
    cap = open_capture(tiny_capture)
    truth = load_truth(tiny_capture)
    assert truth.method == "ground_truth"
    angles, shifts = [], []
    for v in cap.views():
        nom = cap.stage.view_camera(v.group, v.camera)
        tru = truth.views[v]
        np.testing.assert_allclose(tru.K_raw, nom.K)
        dR = tru.R @ nom.R.T
        angles.append(np.degrees(np.arccos(np.clip((np.trace(dR) - 1) / 2, -1, 1))))
        shifts.append(np.linalg.norm(-tru.R.T @ tru.t - nom.center))
    assert 0.02 < np.median(angles) < 2.0
    assert 0.0005 < np.median(shifts) < 0.03
    d = np.asarray(truth.axis.direction)
    assert 0.05 < np.degrees(np.arccos(d[2])) < 1.0
    for g in cap.stage.group_names:
        err = np.linalg.norm(truth.light_positions[g] - cap.stage.light_positions_world(g), axis=-1)
        assert 0.0 < np.median(err) < 0.05


def test_deterministic_for_a_seed(tmp_path: Path, tree_hash) -> None:
    sel = {"groups": "000,040", "cameras": "0,2", "lights": "0-3"}
    a = simulate_capture(tmp_path / "a", "tiny", seed=3, workers=1, progress=False, **sel)
    b = simulate_capture(tmp_path / "b", "tiny", seed=3, workers=2, progress=False, **sel)
    c = simulate_capture(tmp_path / "c", "tiny", seed=4, workers=1, progress=False, **sel)
    assert tree_hash(a) == tree_hash(b)
    assert tree_hash(a) != tree_hash(c)
    cap = open_capture(a)
    assert cap.stage.group_names == ["000", "040"] and cap.stage.camera_ids == ["cam00", "cam02"]
    assert len(cap.stage.lights) == 4


def test_clean_render_is_linear_and_matches_files(tiny_capture: Path) -> None:
    truth = load_truth(tiny_capture)
    scene = load_scene(tiny_capture)
    pos = truth.light_positions["040"]
    i1, i2 = 2, 7
    one = render_clean(tiny_capture, "040", "cam01", pos[[i1]])
    two = render_clean(tiny_capture, "040", "cam01", pos[[i2]], [2.5 * scene.light_intensity])
    both = render_clean(
        tiny_capture, "040", "cam01", pos[[i1, i2]], [scene.light_intensity, 2.5 * scene.light_intensity]
    )
    assert one.max() > 0.05 and two.max() > 0.05
    np.testing.assert_allclose(both, one + two, rtol=1e-5, atol=1e-6)
    assert (both >= 0).all() and np.isfinite(both).all()
    rgb = render_clean(tiny_capture, "040", "cam01", pos[[i1]], [[scene.light_intensity, 0.0, 0.0]])
    np.testing.assert_allclose(rgb[..., 0], one[..., 0], rtol=1e-6, atol=1e-7)
    assert rgb[..., 1:].max() == 0.0
    lt = json.loads((tiny_capture / "ground_truth" / "clean.json").read_text())["lights"][0]
    stored = read_exr(tiny_capture / "ground_truth" / "clean" / "040" / "cam01" / f"{lt:03d}.exr")
    assert stored.dtype == np.float32
    np.testing.assert_allclose(
        render_clean(tiny_capture, "040", "cam01", pos[[lt]]), stored, rtol=1e-5, atol=1e-6
    )


def test_typical_object_pixels_below_cutoff(tiny_capture: Path) -> None:
    cap = open_capture(tiny_capture)
    levels = []
    for lt in range(len(cap.stage.lights)):
        img = read_exr(cap.frame_path(FrameId("000", "cam01", lt))).astype(np.float32)
        m = _mask(tiny_capture, "000", "cam01")
        levels.append(np.percentile(img[m].mean(-1), 90))
    assert 0.02 < np.median(levels) < 1.5


def test_back_lit_frames_transmit_light(tiny_capture: Path) -> None:
    cap = open_capture(tiny_capture)
    truth = load_truth(tiny_capture)
    scene = load_scene(tiny_capture)
    best = None
    for v in cap.views():
        cam_dir = truth.views[v].camera(1).center
        cam_dir = cam_dir / np.linalg.norm(cam_dir)
        om = truth.light_directions(v.group)
        k = int(np.argmin(om @ cam_dir))
        if best is None or om[k] @ cam_dir < best[0]:
            best = (float(om[k] @ cam_dir), v, k)
    cos, v, k = best
    assert cos < -0.6, "tiny needs a light behind the object for some view"
    m = _mask(tiny_capture, v.group, v.camera)
    raw = read_exr(cap.frame_path(FrameId(v.group, v.camera, k))).astype(np.float32).mean(-1)
    bg = np.median(raw[~m])
    # the translucent object (not the stand) glows with transmitted light
    clean = render_clean(tiny_capture, v.group, v.camera, truth.light_positions[v.group][[k]]).mean(-1)
    lo, hi = scene.bounding_box()
    obj = m & (clean > 0)
    assert np.percentile(raw[obj], 75) > 10 * max(bg, 1e-4)
    assert np.percentile(clean[m], 90) > 0.02
    assert lo[2] < 0 < hi[2]


def test_bulbs_in_view_are_saturated(tiny_capture: Path) -> None:
    cap = open_capture(tiny_capture)
    truth = load_truth(tiny_capture)
    checked = 0
    for v in cap.views():
        cam = truth.views[v].camera(1)
        m = _mask(tiny_capture, v.group, v.camera)
        for k, p in enumerate(truth.light_positions[v.group]):
            pc = cam.R @ p + cam.t
            if pc[2] <= 0:
                continue
            u, w = (cam.K @ pc)[:2] / pc[2]
            i, j = int(np.floor(u)), int(np.floor(w))
            if (
                not (2 <= i < cam.width - 2 and 2 <= j < cam.height - 2)
                or m[j - 2 : j + 3, i - 2 : i + 3].any()
            ):
                continue
            img = read_exr(cap.frame_path(FrameId(v.group, v.camera, k))).astype(np.float32)
            assert img[j, i].min() >= cap.stage.saturation, (v, k)
            checked += 1
    listed = json.loads((tiny_capture / "ground_truth" / "nuisances.json").read_text())["bulbs_in_view"]
    assert checked >= 1 and len(listed) >= checked


def _surface_samples(e: Ellipsoid, n: int, rng: np.random.Generator) -> np.ndarray:
    d = rng.standard_normal((n, 3))
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    return np.asarray(e.centre) + d * np.asarray(e.radii)


def test_masks_match_projected_geometry(tiny_capture: Path) -> None:
    import cv2

    cap = open_capture(tiny_capture)
    truth = load_truth(tiny_capture)
    scene = load_scene(tiny_capture)
    rng = np.random.default_rng(0)
    pts = np.concatenate([_surface_samples(e, 40000, rng) for e in scene.body])
    s = scene.stand
    ang = rng.uniform(0, 2 * np.pi, 40000)
    z = rng.uniform(s.z_min, s.z_max, 40000)
    stand = np.stack(
        [s.centre_xy[0] + s.radius * np.cos(ang), s.centre_xy[1] + s.radius * np.sin(ang), z], -1
    )
    pts = np.concatenate([pts, stand])
    for v in list(cap.views())[::5]:
        cam = truth.views[v].camera(1)
        m = _mask(tiny_capture, v.group, v.camera)
        uv = (pts @ cam.R.T + cam.t) @ cam.K.T
        uv = uv[:, :2] / uv[:, 2:]
        ok = (uv[:, 0] >= 0) & (uv[:, 0] < cam.width) & (uv[:, 1] >= 0) & (uv[:, 1] < cam.height)
        ij = np.floor(uv[ok]).astype(int)
        occ = np.zeros_like(m)
        occ[ij[:, 1], ij[:, 0]] = True
        grown = cv2.dilate(m.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
        assert grown[occ].all(), v  # every projected surface point lies in the (1-px grown) mask
        filled = cv2.morphologyEx(occ.astype(np.uint8), cv2.MORPH_CLOSE, np.ones((5, 5), np.uint8)) > 0
        assert (filled & m).sum() > 0.9 * m.sum(), v  # and the projection covers the mask
        assert 0.02 < m.mean() < 0.6


def test_bad_arguments(tmp_path: Path) -> None:
    with pytest.raises(LightstageError, match="unknown simulator preset"):
        simulate_capture(tmp_path / "x", "huge")
    with pytest.raises(LightstageError, match="--lights"):
        simulate_capture(tmp_path / "x", "tiny", lights="3-1")
    with pytest.raises(LightstageError, match="--cameras"):
        simulate_capture(tmp_path / "x", "tiny", cameras="cam99")
    with pytest.raises(LightstageError, match="select a subset"):
        simulate_capture(tmp_path / "x", "paper")
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "f").write_text("x")
    with pytest.raises(LightstageError, match="not an empty directory"):
        simulate_capture(tmp_path / "full", "tiny")


def test_cli(tmp_path: Path) -> None:
    from lightstage.pipelines.cli import main

    out = tmp_path / "cli"
    rc = main(
        [
            "simulate",
            str(out),
            "--preset",
            "tiny",
            "--groups",
            "0",
            "--cameras",
            "cam01",
            "--lights",
            "0-5:5",
            "--quiet",
        ]
    )
    assert rc == 0
    cap = open_capture(out)
    assert [f.light for f in cap.frames()] == [0, 1]
    assert (out / "contact_sheet.png").is_file()
    r = subprocess.run(
        [
            sys.executable,
            "-m",
            "lightstage.pipelines.cli",
            "simulate",
            str(tmp_path / "y"),
            "--preset",
            "nope",
        ],
        capture_output=True,
        text=True,
    )
    assert r.returncode == 2
    assert r.stderr.strip().count("\n") == 0 and r.stderr.startswith("lightstage: error:")


def _hemisphere_views(n: int, rng: np.random.Generator) -> np.ndarray:
    """Cosine-weighted unit directions around +z."""
    u1, u2 = rng.random(n), rng.random(n)
    r, phi = np.sqrt(u1), 2 * np.pi * u2
    return np.stack([r * np.cos(phi), r * np.sin(phi), np.sqrt(1 - u1)], -1)


def test_shading_does_not_create_energy() -> None:
    """White albedo at the top of the head and on the thin fin's rim: the outgoing flux is <= the irradiance for
    a light along the normal, and integrated over all light directions it stays below Lambert's (pi)."""
    from lightstage.capture.presets import fibonacci_cap
    from lightstage.simulator.scene import KIND_OBJECT, default_scene
    from lightstage.simulator.shading import ViewHits, shade

    scene = default_scene()
    parts = {e.name: e for e in scene.body}
    head, fin = parts["head"], parts["fin"]
    rim = np.asarray(fin.centre) + np.array([fin.radii[0] * np.cos(0.3), fin.radii[1] * np.sin(0.3), 0.0])
    rim_n = (rim - np.asarray(fin.centre)) / np.asarray(fin.radii) ** 2
    points = [
        (np.asarray(head.centre) + np.array([0.0, 0.0, head.radii[2]]), np.array([0.0, 0.0, 1.0])),
        (rim, rim_n / np.linalg.norm(rim_n)),
    ]
    rng = np.random.default_rng(0)
    local = _hemisphere_views(2000, rng)
    light_dirs = fibonacci_cap(500, 180.0)
    dist = 1.5
    for x, nrm in points:
        t1 = np.cross(nrm, [0.3, 0.5, 0.8])
        t1 /= np.linalg.norm(t1)
        views = local @ np.stack([t1, np.cross(nrm, t1), nrm])
        n = len(views)
        hits = ViewHits(
            n,
            1,
            np.arange(n),
            np.full(n, KIND_OBJECT, np.int8),
            np.repeat(x[None], n, 0),
            np.repeat(nrm[None].astype(np.float32), n, 0),
            views.astype(np.float32),
            np.ones((n, 3), np.float32),
        )

        def flux(light_dir: np.ndarray, hits: ViewHits = hits, x: np.ndarray = x) -> np.ndarray:
            rad = shade(scene, hits, x + dist * light_dir, dist**2)  # unit irradiance at normal incidence
            return np.pi * rad.mean(0)  # cosine-weighted estimate of the integral of L cos, per channel

        head_on = flux(nrm)
        assert (head_on > 0.3).all() and (head_on <= 1.0).all()
        total = np.mean([flux(d) for d in light_dirs], axis=0) * 4 * np.pi
        assert (total <= np.pi).all(), total / np.pi


def test_lens_flare_brightens_the_background(tiny_capture: Path) -> None:
    cap = open_capture(tiny_capture)
    flares = json.loads((tiny_capture / "ground_truth" / "nuisances.json").read_text())["flares"]
    assert flares, "tiny should contain some frames with lens flare"
    f = max(flares, key=lambda r: r["strength"])
    m = _mask(tiny_capture, f["group"], f["camera"])
    lit = read_exr(cap.frame_path(FrameId(f["group"], f["camera"], f["light"]))).astype(np.float32)
    flare_lights = {r["light"] for r in flares if (r["group"], r["camera"]) == (f["group"], f["camera"])}
    other = next(k for k in range(len(cap.stage.lights)) if k not in flare_lights)
    plain = read_exr(cap.frame_path(FrameId(f["group"], f["camera"], other))).astype(np.float32)
    assert lit[~m].mean() > 3 * plain[~m].mean()
