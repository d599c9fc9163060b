"""`lightstage view`: the bundle of a small simulated capture (a shaded sphere under 12 stage lights in two
groups) and of a briefly trained model, the command line, and the page itself driven in a real headless
Chromium (controls set through the page, screenshot compared with the Python reference)."""

from __future__ import annotations

import json
import threading

import numpy as np
import pytest

from lightstage.errors import LightstageError
from lightstage.frames import write_exr
from lightstage.ids import FrameId
from lightstage.records.calibration import Calibration
from lightstage.records.processed import read_processed
from lightstage.tonemap import tonemap_u8
from lightstage.viewer.build import ViewerConfig, build_key, build_viewer, is_current
from lightstage.viewer.reference import Bundle, Settings, reference_image, settings_weights

SPHERE_CENTRE = np.array([0.02, -0.01, 0.03])
SPHERE_RADIUS = 0.1


def shade_frames(work) -> None:
    """Replace the fixture's random frames by a textured Lambertian sphere on a dimly lit background, so the
    basis is smooth and close to low rank like a real one."""
    from lightstage.cameras import pixel_centers, pixel_rays

    calib = Calibration.load(work.calibration)
    for view, vc in calib.views.items():
        cam = vc.camera()
        o, d = pixel_rays(pixel_centers(cam.width, cam.height).reshape(-1, 2), cam.K, cam.R, cam.t)
        oc = o - SPHERE_CENTRE
        b = np.sum(oc * d, -1)
        disc = b * b - (np.sum(oc * oc, -1) - SPHERE_RADIUS**2)
        hit = disc > 0
        n = (oc + (-b - np.sqrt(np.clip(disc, 0, None)))[:, None] * d) / SPHERE_RADIUS
        albedo = np.stack(
            [0.6 + 0.3 * np.sin(12 * n[:, 0]), 0.5 + 0.2 * np.cos(9 * n[:, 1]), 0.4 + 0 * n[:, 2]], 1
        )
        for light, omega in enumerate(calib.light_directions(view.group)):
            shade = np.clip(n @ omega, 0, None)[:, None] * albedo * hit[:, None]
            bg = 0.04 * (1.2 + omega[2]) * (0.8 + 0.2 * d[:, :1]) * ~hit[:, None]
            rgb = (shade + bg).reshape(cam.height, cam.width, 3).astype(np.float32)
            sat = np.zeros((cam.height, cam.width, 1), np.float32)
            write_exr(
                work.frame(FrameId(view.group, view.camera, light)), np.dstack([rgb, sat]), channels="RGBS"
            )


@pytest.fixture(scope="module")
def capture_work(tmp_path_factory):
    from support.fixtures import make_synthetic_work

    work, _ = make_synthetic_work(
        tmp_path_factory.mktemp("viewer"), num_cameras=2, num_lights=12, num_groups=2
    )
    shade_frames(work)
    return work


@pytest.fixture(scope="module")
def capture_bundle(capture_work, tmp_path_factory):
    bundle = tmp_path_factory.mktemp("bundle") / "viewer"
    config = ViewerConfig(source="capture", camera="cam00", tolerance=0.001)
    build_viewer(capture_work, config, bundle, progress=False)
    return bundle


def _frames(work, view_id: str) -> np.ndarray:
    group, camera = view_id.split("/")
    return np.stack([read_processed(work.frame(FrameId(group, camera, k)))[0] for k in range(12)])


def test_bundle_layout_and_python_reference(capture_work, capture_bundle):
    manifest = json.loads((capture_bundle / "manifest.json").read_text())
    (s,) = manifest["sets"]
    assert s["source"] == "capture" and s["basis_lights"] == 12 and len(s["views"]) == 2
    assert [v["view_id"] for v in s["views"]] == ["000/cam00", "180/cam00"]
    assert len(s["bases"]) == 2  # the lights turn with the rig: one basis per group
    for f in ("index.html", "viewer.js", "viewer.css"):
        assert (capture_bundle / f).is_file()
    bundle = Bundle(capture_bundle)
    for v, view in enumerate(s["views"]):
        assert view["relative_error"] <= 0.001 and view["ab"] == {"set": 0, "view": v}
        frames = _frames(capture_work, view["view_id"])
        settings = Settings(view=v, mode="both", azimuth_deg=100, elevation_deg=20, rotate_deg=77)
        exact, _ = reference_image(bundle, settings, frames)
        compressed, _ = reference_image(bundle, settings)
        assert np.linalg.norm(compressed - exact) / np.linalg.norm(exact) < 2e-3
        # the table the page reads holds the same envmap weights the reference computes
        table = np.fromfile(
            capture_bundle / manifest["envmaps"][0]["tables"]["capture"][view["basis"]], "<f4"
        )
        env_only = settings_weights(bundle, Settings(view=v, mode="envmap", rotate_deg=77))
        assert np.allclose(table.reshape(360, 12, 3)[77], env_only, rtol=1e-5, atol=1e-9)


def test_cli_exports_reuses_and_refuses_bad_input(capture_work, tmp_path, capsys):
    from lightstage.pipelines.cli import main

    out = tmp_path / "site"
    args = ["view", str(capture_work.root), "--export", str(out), "--views", "1", "-q"]
    assert main(args) == 0 and (out / "manifest.json").is_file()
    assert "wrote" in capsys.readouterr().out
    assert main(args) == 0 and "up to date" in capsys.readouterr().out
    # no build options: the bundle's own (the demo's, say) are kept, not the defaults; a killed build's
    # leftovers are removed by the next build
    assert main(["view", str(capture_work.root), "--export", str(out), "-q"]) == 0
    assert "up to date" in capsys.readouterr().out
    (tmp_path / ".site.tmp-999999999").mkdir()
    assert main([*args, "--rebuild"]) == 0 and not (tmp_path / ".site.tmp-999999999").exists()
    capsys.readouterr()
    assert main(["view", str(capture_work.root), "--source", "model", "--export", str(tmp_path / "x")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "lightstage: error:" in err and "checkpoint" in err
    assert (
        main(["view", str(capture_work.root), "--envmap", str(tmp_path / "no.exr"), "--export", str(out)])
        == 2
    )
    assert "no.exr" in capsys.readouterr().err
    (tmp_path / "other").mkdir()
    (tmp_path / "other" / "keep.txt").write_text("x")
    assert main(["view", str(capture_work.root), "--export", str(tmp_path / "other"), "-q"]) == 2
    assert (tmp_path / "other" / "keep.txt").is_file() and "not a viewer bundle" in capsys.readouterr().err
    with pytest.raises(LightstageError, match="--source"):
        ViewerConfig(source="film")
    key = build_key(capture_work, ViewerConfig(views=1))
    assert not is_current(out, {**key, "config": {**key["config"], "tolerance": 0.5}})


def test_model_source_renders_an_orbit_with_novel_views(tmp_path, capsys):
    """A briefly trained model without a calibration: an orbit ring of novel views under the stage basis."""
    from support.synthetic import SyntheticSphere
    from support.training import micro_config

    from lightstage.pipelines.cli import main
    from lightstage.training.inference import load_trained
    from lightstage.training.trainer import fit
    from lightstage.workdir import WorkDir

    work = WorkDir.at(tmp_path / "work")
    sphere = SyntheticSphere(batch_size=64)
    fit(micro_config(3), sphere, work.train_dir, sphere.centre, sphere.scale, progress=False)
    out = tmp_path / "site"
    args = ["view", str(work.root), "--orbit-views", "2", "--orbit-size", "16x12", "--basis-lights", "8"]
    assert main([*args, "--tolerance", "0", "--export", str(out), "-q"]) == 0
    manifest = json.loads((out / "manifest.json").read_text())
    (s,) = manifest["sets"]
    assert s["source"] == "model" and s["basis_lights"] == 8 and len(s["views"]) == 2
    assert all(v["ab"] is None and v["view_id"] is None for v in s["views"])
    bundle = Bundle(out)
    basis = bundle.basis(0, 1)
    model = load_trained(work)
    from lightstage.training.view_specs import parse_camera

    camera = parse_camera("orbit:az=180,elev=20,size=16x12", None, model).camera
    direction = basis.directions[3]
    az, el = np.degrees(np.arctan2(direction[1], direction[0])), np.degrees(np.arcsin(direction[2]))
    img, _ = reference_image(bundle, Settings(view=1, azimuth_deg=az, elevation_deg=el))
    ref = model.image_from_camera(camera, direction)
    assert np.abs(img - ref).max() <= 2e-3 * np.abs(ref).max() + 1e-7


# ---- the page in a real browser ------------------------------------------------------------------------
@pytest.fixture(scope="module")
def page(capture_bundle):
    from support.browser import Chromium, find_chromium

    from lightstage.viewer.serve import make_server

    exe = find_chromium()
    if exe is None:
        pytest.skip("no Chromium-family browser installed (apt-get install chromium; .ci/run installs it)")
    server = make_server(capture_bundle, 0)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        with Chromium(exe) as browser:
            p = browser.open(f"http://127.0.0.1:{server.server_address[1]}/")
            p.wait_for("window.lightstage && (window.lightstage.ready || window.lightstage.error)", 120)
            assert p.evaluate("lightstage.error") is None, p.evaluate("lightstage.error")
            yield p
    finally:
        server.shutdown()
        server.server_close()


SET_CONTROL = """(() => {{
  const e = document.getElementById({id!r});
  if (e.type === "checkbox") e.checked = {value!r} === "on"; else e.value = {value!r};
  e.dispatchEvent(new Event(e.type === "checkbox" ? "change" : "input"));
}})()"""


def _set(page, **controls: str) -> None:
    for key, value in controls.items():
        page.evaluate(SET_CONTROL.format(id=key.replace("_", "-"), value=str(value)))
    page.wait_for("lightstage.idle()", 60)


def _canvas(page) -> np.ndarray:
    import cv2

    rect = page.evaluate(
        "(() => { const r = document.getElementById('view').getBoundingClientRect();"
        " return {x: r.left, y: r.top, width: r.width, height: r.height}; })()"
    )
    png = page.screenshot(rect)
    return cv2.cvtColor(cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)


def _psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = float(np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2))
    return float("inf") if mse == 0 else 10 * np.log10(255.0**2 / mse)


def test_page_matches_the_python_reference(page, capture_work, capture_bundle):
    """A light and an envmap rotation set through the page's controls: the screenshot equals the image Python
    computes for the same settings from the captured frames themselves (>= 40 dB, tonemapped)."""
    info = page.evaluate("document.getElementById('source-info').textContent")
    assert "captured OLAT frames" in info and "Basis lights: 12" in info
    assert page.evaluate("lightstage.frameTimeMs") > 0
    _set(page, zoom=1, view_index=1, mode="both", light_az=100, light_el=20, env_rot=77, exposure=0.5)
    state = page.evaluate("lightstage.state()")
    assert (state["view"], state["az"], state["el"], state["rot"], state["mode"]) == (1, 100, 20, 77, "both")
    shot = _canvas(page)
    bundle = Bundle(capture_bundle)
    frames = _frames(capture_work, "180/cam00")
    settings = Settings(
        view=1, mode="both", azimuth_deg=100, elevation_deg=20, rotate_deg=77, exposure_stops=0.5
    )
    hdr, exposure = reference_image(bundle, settings, frames)
    assert exposure == pytest.approx(state["exposure"], rel=1e-9)
    ref = tonemap_u8(hdr, exposure)
    assert shot.shape == ref.shape
    psnr = _psnr(shot, ref)
    assert psnr >= 40.0, psnr
    # the controls matter: another rotation or light is a clearly different picture
    for other in (dict(rotate_deg=167), dict(azimuth_deg=-60)):
        wrong = tonemap_u8(*reference_image(bundle, Settings(**{**settings.__dict__, **other}), frames))
        assert _psnr(shot, wrong) < psnr - 10
    ms = page.evaluate("lightstage.frameTimeMs")
    print(f"page vs Python: {psnr:.1f} dB; frame time {ms:.2f} ms, {page.evaluate('lightstage.renderer')}")


def test_ab_shows_the_captured_frame_of_the_snapped_light(page, capture_work):
    _set(page, zoom=1, view_index=0, mode="point", light_az=10, light_el=35, light_int=1, exposure=0)
    _set(page, snap="on")
    state = page.evaluate("lightstage.state()")
    page.evaluate("document.getElementById('ab').click()")
    page.wait_for("lightstage.idle()", 60)
    shot_b = _canvas(page)
    assert "captured frame" in page.evaluate("document.getElementById('caption').textContent")
    page.evaluate("document.getElementById('ab').click()")
    page.wait_for("lightstage.idle()", 60)
    shot_a = _canvas(page)
    calib = Calibration.load(capture_work.calibration)
    dirs = calib.light_directions("000")
    light = int(np.argmax(dirs @ np.array(_azel(state["az"], state["el"]))))
    frame = read_processed(capture_work.frame(FrameId("000", "cam00", light)))[0]
    truth = tonemap_u8(frame, state["exposure"])
    print(f"A/B: captured frame {_psnr(shot_b, truth):.1f} dB, snapped relit {_psnr(shot_a, truth):.1f} dB")
    assert _psnr(shot_b, truth) >= 40.0
    assert _psnr(shot_a, truth) >= 40.0  # snapped: the relit image at a basis light is that frame
    _set(page, snap="off")


def _azel(az: float, el: float) -> list[float]:
    a, e = np.deg2rad(az), np.deg2rad(el)
    return [np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)]


def test_capture_lights_picks_a_spread_subset_and_oversized_bases_are_refused(capture_work, tmp_path):
    from lightstage.viewer.sources import check_basis_size

    manifest = build_viewer(
        capture_work, ViewerConfig(source="capture", views=1, capture_lights=5), tmp_path / "v", False
    )
    (basis,) = manifest["sets"][0]["bases"]
    assert basis["lights"] == 5 and len(set(basis["light_indices"])) == 5
    assert manifest["sets"][0]["views"][0]["coefficients"].__len__() % 5 == 0
    with pytest.raises(LightstageError, match="GiB per view"):
        check_basis_size(331, 2048, 1366, "view 000/cam00")


def test_views_load_progressively(page):
    """After the first view is drawn the page fetches every other view in the background and keeps it."""
    page.wait_for("lightstage.prefetched", 60)
    assert page.evaluate("[lightstage.loaded, lightstage.total]") == [2, 2]
    assert page.evaluate("lightstage.prefetchFailed") == []
    assert page.evaluate("lightstage.firstDrawMs") > 0
    assert "views loaded: 2/2" in page.evaluate("document.getElementById('loading').textContent")


def test_first_view_shows_alone(capture_bundle, tmp_path):
    """A bundle holding only the manifest, the page and the first view's file: the page draws the first view;
    the missing views are reported as not loaded, not as a broken page."""
    import shutil

    from support.browser import Chromium, find_chromium

    from lightstage.viewer.serve import make_server

    exe = find_chromium()
    if exe is None:
        pytest.skip("no Chromium-family browser installed (apt-get install chromium; .ci/run installs it)")
    site = tmp_path / "site"
    shutil.copytree(capture_bundle, site)
    views = json.loads((site / "manifest.json").read_text())["sets"][0]["views"]
    for view in views[1:]:
        (site / view["file"]).unlink()
    server = make_server(site, 0)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    try:
        with Chromium(exe) as browser:
            p = browser.open(f"http://127.0.0.1:{server.server_address[1]}/")
            p.wait_for("window.lightstage && (window.lightstage.prefetched || window.lightstage.error)", 120)
            assert p.evaluate("lightstage.error") is None
            assert p.evaluate("[lightstage.drawn >= 1, lightstage.loaded]") == [True, 1]
            assert p.evaluate("lightstage.prefetchFailed") == [views[1]["file"]]
            assert "1 failed" in p.evaluate("document.getElementById('loading').textContent")
    finally:
        server.shutdown()
        server.server_close()
