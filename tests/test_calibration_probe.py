"""Mirror-ball probe: image measurements (preprocess/probe.py) and the geometry that turns them into rays towards
the lights (calibration/probe.py, calibration/light_rays.py), on exact synthetic data."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from scipy.special import erf

from lightstage.calibration.light_rays import locate_lights
from lightstage.calibration.probe import ProbeData, fit_ball_cone, probe_rays
from lightstage.cameras import camera_center, look_at
from lightstage.errors import LightstageError
from lightstage.preprocess.probe import ball_highlight, ball_outline
from lightstage.simulator.probe_optics import specular_point

F = 2000.0
K = np.array([[F, 0, 384.0], [0, F, 256.0], [0, 0, 1]])
RADIUS = 0.05


def _rig(n: int = 8) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """n cameras 1.1 m from the origin on two rings, looking at it."""
    cams = {}
    for i in range(n):
        a, el = 2 * np.pi * i / n, np.deg2rad(10 if i % 2 else 40)
        c = 1.1 * np.array([np.cos(el) * np.cos(a), np.cos(el) * np.sin(a), np.sin(el)])
        cams[f"cam{i:02d}"] = look_at(c, np.zeros(3))
    return cams


def _project(p: np.ndarray, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    q = K @ (R @ p + t)
    return q[:2] / q[2]


def _outline(cam: tuple[np.ndarray, np.ndarray], centre: np.ndarray, n: int = 400) -> np.ndarray:
    """Exact outline pixels of the sphere: rays on its tangent cone."""
    R, t = cam
    c = R @ centre + t
    D = np.linalg.norm(c)
    a = c / D
    beta = np.arcsin(RADIUS / D)
    e1 = np.cross(a, [0, 0, 1.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(a, e1)
    phi = np.linspace(0, 2 * np.pi, n, endpoint=False)
    d = np.cos(beta) * a + np.sin(beta) * (np.cos(phi)[:, None] * e1 + np.sin(phi)[:, None] * e2)
    q = d @ K.T
    return q[:, :2] / q[:, 2:]


def _probe(cams, lights: np.ndarray, centres: dict[str, np.ndarray]) -> ProbeData:
    data = ProbeData(RADIUS, sorted(centres))
    for pos, c in centres.items():
        for cam, (R, t) in cams.items():
            data.outlines[pos, cam] = _outline((R, t), c)
            x, valid = specular_point(c, RADIUS, camera_center(R, t), lights)
            assert valid.all()
            data.highlights[pos, cam] = {li: tuple(_project(p, R, t)) for li, p in enumerate(x)}
    return data


def _scene():
    cams = _rig()
    rng = np.random.default_rng(3)
    d = rng.normal(size=(6, 3))
    d[:, 2] = np.abs(d[:, 2])
    lights = 1.5 * d / np.linalg.norm(d, axis=1, keepdims=True)
    centres = {g: 0.09 * np.array([np.cos(np.deg2rad(g)), np.sin(np.deg2rad(g)), 0.0]) for g in (0, 120, 240)}
    return cams, lights, {f"{g:03d}": c for g, c in centres.items()}


def test_fit_ball_cone_recovers_the_centre_direction_and_distance():
    cams = _rig(1)
    cam = next(iter(cams.values()))
    centre = np.array([0.05, -0.03, 0.02])
    cone = fit_ball_cone(_outline(cam, centre), K)
    c = cam[0] @ centre + cam[1]
    np.testing.assert_allclose(cone.axis, c / np.linalg.norm(c), atol=1e-10)
    assert RADIUS / np.sin(cone.half_angle) == pytest.approx(np.linalg.norm(c), rel=1e-9)
    assert cone.rms_px < 1e-6
    # A stray blob on the outline (a bulb next to the ball) is left out.
    pts = _outline(cam, centre)
    pts[:10] += 3.0
    assert np.linalg.norm(fit_ball_cone(pts, K).axis - cone.axis) < 1e-7


def test_probe_rays_locate_every_light_exactly_from_exact_measurements():
    cams, lights, centres = _scene()
    rays, report = probe_rays(_probe(cams, lights, centres), cams, {c: (K, np.zeros(5)) for c in cams})
    assert report["rays"] == len(rays) == len(cams) * len(lights) * len(centres)
    for pos, c in centres.items():
        np.testing.assert_allclose(report["ball_centres_rig_m"][pos], c, atol=1e-6)
    nominal = lights + 0.004  # off by 7 mm, with a weak prior: the rays decide
    est = locate_lights(rays, nominal, prior_sigma_m=1.0)
    assert np.abs(est.positions - lights).max() < 1e-5
    assert not est.rejected_rays and len(est.sources[0]) == 24


def test_probe_rays_do_not_magnify_camera_rotation_errors():
    """Each camera's own outline fixes the ball's direction, so a small rotation error of a camera turns its
    reflected rays by that error only (a triangulated centre would turn them ~40x more)."""
    cams, lights, centres = _scene()
    data = _probe(cams, lights, centres)
    rng = np.random.default_rng(0)
    err = np.deg2rad(0.01)  # SfM's shape error per camera
    wrong = {}
    for cam, (R, t) in cams.items():
        dR = Rotation.from_rotvec(err * rng.normal(size=3) / np.sqrt(3)).as_matrix()
        c = camera_center(R, t)
        wrong[cam] = (dR @ R, -(dR @ R) @ c)
    rays, _ = probe_rays(data, wrong, {c: (K, np.zeros(5)) for c in cams})
    est = locate_lights(rays, lights, prior_sigma_m=0.003)
    lateral = []
    for li, p in enumerate(lights):
        e = est.positions[li] - p
        u = p / np.linalg.norm(p)
        lateral.append(np.linalg.norm(e - (e @ u) * u))
    assert max(lateral) < 0.5e-3  # 0.01 deg at 1.5 m is 0.26 mm


def test_ball_outline_and_highlight_are_sub_pixel():
    h, w = 200, 240
    u0, v0, rad = 121.3, 97.8, 40.0
    ss = 8  # supersampled disc
    yy, xx = np.mgrid[0 : h * ss, 0 : w * ss]
    disc = ((xx + 0.5) / ss - u0) ** 2 + ((yy + 0.5) / ss - v0) ** 2 <= rad**2
    img = disc.reshape(h, ss, w, ss).mean(axis=(1, 3)) * 0.5 + 0.01
    img = img + np.random.default_rng(1).normal(0, 0.002, img.shape)
    uv, (uc, vc, r) = ball_outline(img.astype(np.float32))
    A = np.column_stack([2 * uv, np.ones(len(uv))])  # circle fit: |x|^2 = 2 c.x + k
    cu, cv, _ = np.linalg.lstsq(A, (uv**2).sum(1), rcond=None)[0]
    assert np.hypot(cu - u0, cv - v0) < 0.02
    assert np.abs(np.hypot(uv[:, 0] - u0, uv[:, 1] - v0) - rad).mean() < 0.05 and abs(r - rad) < 1

    # A Gaussian spot (sigma 0.8 px) integrated over the pixels, on the dark ball, plus noise.
    hu, hv, s = 130.37, 90.61, 0.8
    ex = erf((np.arange(w + 1) - hu) / (np.sqrt(2) * s))
    ey = erf((np.arange(h + 1) - hv) / (np.sqrt(2) * s))
    spot = np.outer(np.diff(ey), np.diff(ex)) / 4 * 12.0
    dark = 0.001 + np.random.default_rng(2).normal(0, 0.002, (h, w))
    u, v, snr = ball_highlight((dark + spot).astype(np.float32), (uc, vc, r), saturation=4.4)
    assert np.hypot(u - hu, v - hv) < 0.02 and snr > 100
    with pytest.raises(LightstageError, match="clipped"):
        ball_highlight((dark + 10 * spot).astype(np.float32), (uc, vc, r), saturation=4.4)
    with pytest.raises(LightstageError, match="no highlight"):
        ball_highlight(dark.astype(np.float32), (uc, vc, r), saturation=4.4)
    with pytest.raises(LightstageError, match="no bright ball"):
        ball_outline(dark.astype(np.float32))


@pytest.fixture(scope="module")
def tiny_probe_work(tiny_capture, tmp_path_factory):
    """The tiny capture (with its simulated probe) preprocessed."""
    from lightstage.preprocess.config import PreprocessConfig
    from lightstage.preprocess.run import run_preprocess
    from lightstage.workdir import WorkDir

    work = WorkDir.at(tmp_path_factory.mktemp("probe") / "work")
    work.root.mkdir()
    work.capture_pointer.write_text(str(tiny_capture))
    summary = run_preprocess(work, PreprocessConfig(), progress=False)
    return work, summary


def test_preprocess_measures_the_probe_at_its_true_highlights(tiny_capture, tiny_probe_work):
    import json

    from lightstage.capture.layout import open_capture
    from lightstage.preprocess.probe import load_view_record, run_probe

    work, _ = tiny_probe_work
    report = json.loads(work.report("preprocess").read_text())["probe"]
    assert report["views"] == 12 and report["views_without_ball"] == 0  # 3 positions x 4 cameras
    truth = json.loads((tiny_capture / "ground_truth" / "probe.json").read_text())
    errs, seen = [], 0
    for h in truth["highlights"]:
        rec = load_view_record(work.probe_view(h["position"], h["camera"]))
        got = rec.highlights.get(str(h["light"]))
        if h["visible"] and got is not None:
            errs.append(np.hypot(got[0] - h["uv"][0], got[1] - h["uv"][1]))
        seen += got is not None
    assert seen >= 0.9 * len(truth["highlights"]) and max(errs) < 0.05
    # Resumable: nothing is measured again; a changed frame is.
    again = run_probe(work, open_capture(tiny_capture), progress=False)
    assert again["views_measured_now"] == 0 and again["views"] == 12


def test_calibration_names_missing_probe_measurements(tiny_capture, tiny_probe_work, tmp_path):
    import shutil

    from lightstage.calibration.probe import load_probe
    from lightstage.capture.layout import open_capture
    from lightstage.workdir import WorkDir

    work, _ = tiny_probe_work
    copy = WorkDir.at(tmp_path / "w")
    shutil.copytree(work.probe_dir, copy.probe_dir)
    data = load_probe(copy, open_capture(tiny_capture))
    assert data.radius_m == 0.05 and len(data.outlines) == 12
    copy.probe_view("120", "cam02").unlink()
    with pytest.raises(LightstageError, match=r"no probe measurements for 1 views \(120/cam02\).*preprocess"):
        load_probe(copy, open_capture(tiny_capture))


def test_refining_the_ball_distances_undoes_camera_position_errors():
    """Cameras 0.1 mm nearer or farther than they are put the mirror's hit points in the wrong place (the rays
    turn by ~1 mrad; the ball's triangulated centre does not notice); fitting each view's camera-to-ball
    distance together with the lights recovers the lights."""
    cams, lights, centres = _scene()
    data = _probe(cams, lights, centres)
    rng = np.random.default_rng(4)
    moved = {}
    for cam, (R, t) in cams.items():
        c = camera_center(R, t)
        c = c * (1 + 1e-4 * rng.choice([-1, 1]) / np.linalg.norm(c))  # 0.1 mm along the line to the centre
        moved[cam] = (R, -R @ c)
    intr = {c: (K, np.zeros(5)) for c in cams}
    nominal = lights + 0.002 * rng.normal(size=lights.shape)

    def error_mm(**kw) -> float:
        rays, report = probe_rays(data, moved, intr, 0.01, 0.0, **kw)
        est = locate_lights(rays, nominal, prior_sigma_m=0.1)  # a weak prior: the rays decide
        return 1000 * float(np.linalg.norm(est.positions - lights, axis=1).max()), report

    plain, _ = error_mm()
    refined, report = error_mm(nominal_lights=nominal, light_sigma_mm=100.0)
    assert report["distances_refined"] and report["distance_change_mm"]["max"] > 0.01
    assert refined < 0.5 * plain and refined < 0.3, (plain, refined)  # measured 0.60 -> 0.20 mm
