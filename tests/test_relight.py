"""Envmap relighting and novel-view rendering against an analytic fake model (a Lambertian sphere whose
OLAT image is a known function of the light direction), implementing the RelightableModel protocol."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from lightstage.cameras import PinholeCamera, camera_center, pixel_centers, pixel_rays
from lightstage.errors import LightstageError
from lightstage.training.envmap import (
    EnvMap,
    all_pixel_lights,
    load_envmap,
    median_cut,
    pixel_directions,
    row_solid_angles,
)
from lightstage.training.novel_views import RenderConfig, run_render
from lightstage.training.relight import (
    RelightableModel,
    RelightConfig,
    parse_lights_option,
    relative_l2,
    relight_image,
    run_relight,
)
from lightstage.training.view_specs import (
    load_scene_info,
    orbit_camera,
    parse_camera,
    parse_light,
    rotate_camera_about_z,
)
from lightstage.workdir import WorkDir


class FakeSphere:
    """Lambertian sphere of radius `radius` at `centre` with RGB albedo; background 0; density a soft ball."""

    def __init__(self, centre=(0.05, -0.02, 0.1), radius=0.3, albedo=(0.8, 0.5, 0.3)):
        self.centre = np.asarray(centre, np.float64)
        self.scale = 0.5
        self.radius = radius
        self.albedo = torch.tensor(albedo, dtype=torch.float32)
        self.calls = 0

    def render_rays(self, origins, directions, light_directions, chunk=65536):
        o = torch.as_tensor(origins, dtype=torch.float32)
        d = torch.as_tensor(directions, dtype=torch.float32)
        light = torch.as_tensor(light_directions, dtype=torch.float32)
        oc = o - torch.as_tensor(self.centre, dtype=torch.float32)
        b = (oc * d).sum(-1)
        c = (oc * oc).sum(-1) - self.radius**2
        disc = b * b - c
        hit = disc > 0
        t = -b - torch.sqrt(torch.clamp(disc, min=0))
        n = (oc + t[:, None] * d) / self.radius
        shade = torch.clamp((n * light).sum(-1), min=0) * hit
        return shade[:, None] * self.albedo

    def density(self, points_world):
        p = torch.as_tensor(points_world, dtype=torch.float32)
        r = torch.linalg.norm(p - torch.as_tensor(self.centre, dtype=torch.float32, device=p.device), dim=-1)
        return 100.0 * torch.sigmoid((self.radius - r) / 0.01)

    def image_from_camera(self, camera, light_direction):
        self.calls += 1
        o, d = pixel_rays(
            pixel_centers(camera.width, camera.height).reshape(-1, 2), camera.K, camera.R, camera.t
        )
        light = np.broadcast_to(np.asarray(light_direction, np.float32), d.shape)
        rgb = self.render_rays(
            torch.from_numpy(o).float(), torch.from_numpy(d).float(), torch.from_numpy(light.copy())
        )
        return rgb.numpy().reshape(camera.height, camera.width, 3)


def _camera(size=(40, 30)) -> PinholeCamera:
    return orbit_camera(np.array([0.05, -0.02, 0.1]), 30.0, 20.0, 1.6, 30.0, size)


def _sky(h=16, w=32) -> np.ndarray:
    """A smooth sky (brighter and bluer upwards), a dim ground and a small warm sun."""
    d = pixel_directions(h, w)
    img = np.empty((h, w, 3))
    up = np.clip(d[..., 2], 0, 1)[..., None]
    img[:] = 0.2 + 0.8 * up * np.array([0.6, 0.8, 1.0])
    img[d[..., 2] < 0] = [0.15, 0.12, 0.1]
    sun = np.array([0.5, 0.3, 0.81])
    img[d @ (sun / np.linalg.norm(sun)) > np.cos(np.deg2rad(12))] = [40.0, 35.0, 25.0]
    return img


def test_fake_implements_the_protocol():
    assert isinstance(FakeSphere(), RelightableModel)


def test_delta_envmap_equals_olat_times_factor():
    model, cam = FakeSphere(), _camera()
    h, w = 16, 32
    r, c = 5, 9
    radiance = np.array([7.0, 3.0, 1.5])
    img = np.zeros((h, w, 3))
    img[r, c] = radiance
    env = EnvMap(img)
    factor = 1.5**2  # capture lights at 1.5 m with unit intensity
    omega = row_solid_angles(h, w)[r]
    olat = model.image_from_camera(cam, env.directions()[r, c].astype(np.float32)).astype(np.float64)
    expected = olat * radiance * omega * factor
    assert expected.max() > 0.01
    for lights in (median_cut(env, 16), median_cut(env, 1), all_pixel_lights(env)):
        out = relight_image(model, cam, lights, factor)
        assert out.dtype == np.float32
        np.testing.assert_allclose(out, expected, rtol=2e-6, atol=1e-7)


def test_relighting_is_linear_in_the_envmap():
    model, cam = FakeSphere(), _camera()
    rng = np.random.default_rng(0)
    e1 = _sky()
    e2 = rng.gamma(0.5, 1.0, size=e1.shape)
    a, b = 0.7, 2.5
    f = 2.25
    r1 = relight_image(model, cam, all_pixel_lights(EnvMap(e1)), f).astype(np.float64)
    r2 = relight_image(model, cam, all_pixel_lights(EnvMap(e2)), f).astype(np.float64)
    r12 = relight_image(model, cam, all_pixel_lights(EnvMap(a * e1 + b * e2)), f)
    np.testing.assert_allclose(r12, a * r1 + b * r2, rtol=1e-5, atol=1e-6)
    # median cut: cuts depend only on the map's shape, so scaling the map scales the result exactly
    k1 = relight_image(model, cam, median_cut(EnvMap(e1), 32), f).astype(np.float64)
    k2 = relight_image(model, cam, median_cut(EnvMap(3.0 * e1), 32), f)
    np.testing.assert_allclose(k2, 3.0 * k1, rtol=1e-5, atol=1e-6)


def test_k_light_error_shrinks_as_k_grows():
    model, cam = FakeSphere(), _camera((32, 24))
    env = EnvMap(_sky())
    ref = relight_image(model, cam, all_pixel_lights(env), 2.25)
    errors = [
        relative_l2(relight_image(model, cam, median_cut(env, k), 2.25), ref) for k in (1, 4, 16, 64, 256)
    ]
    assert all(b < a for a, b in zip(errors, errors[1:], strict=False)), errors
    assert errors[-1] < 0.02 and errors[0] > 5 * errors[-1]
    assert relative_l2(ref, ref) == 0.0


def test_rotation_moves_the_lighting():
    model, cam = FakeSphere(), _camera()
    img = np.zeros((16, 32, 3))
    img[7, 16] = 10.0  # equator, just right of longitude 0 (+x)
    base = relight_image(model, cam, median_cut(EnvMap(img), 4), 1.0)
    turned = relight_image(model, cam, median_cut(EnvMap(img, rotate_deg=90.0), 4), 1.0)
    d = EnvMap(img, rotate_deg=90.0).directions()[7, 16]
    np.testing.assert_allclose(
        turned,
        model.image_from_camera(cam, d.astype(np.float32)) * 10.0 * row_solid_angles(16, 32)[7],
        rtol=2e-6,
        atol=1e-7,
    )
    assert not np.allclose(base, turned)


def test_real_envmaps_relight_without_error(shared_data):
    model, cam = FakeSphere(), _camera((24, 18))
    for name in ("KernerEnvLatLong.exr", "StageEnvLatLong.exr"):
        env = load_envmap(shared_data / "envmaps" / name, (32, 16), rotate_deg=45.0)
        ref = relight_image(model, cam, all_pixel_lights(env), 2.25)
        out = relight_image(model, cam, median_cut(env, 64), 2.25)
        assert np.all(np.isfinite(out)) and out.min() >= 0 and out.max() > 0
        assert relative_l2(out, ref) < 0.1


def test_parse_lights_option():
    assert parse_lights_option("16,64,all") == [16, 64, "all"]
    assert parse_lights_option(32) == [32]
    for bad in ("12", "x", "0"):
        with pytest.raises(LightstageError):
            parse_lights_option(bad)


def _work_with_calibration(tmp_path):
    """A work dir with a one-view calibration (processed 32x24) and lights on a 1.5 m sphere."""
    from lightstage.ids import ViewId
    from lightstage.records.calibration import Calibration, ViewCalibration
    from lightstage.rig import TurntableAxis

    cam = orbit_camera(np.array([0.05, -0.02, 0.1]), 10.0, 15.0, 1.6, 30.0, (128, 96))
    lights = np.array([[1.5, 0, 0], [0, 0, 1.5], [0, 1.5, 0]])
    calib = Calibration(
        method="ground_truth",
        views={ViewId("000", "cam00"): ViewCalibration(cam.K, cam.R, cam.t, 128, 96)},
        light_positions={"000": lights},
        axis=TurntableAxis(),
        yaws_deg={"000": 0.0},
    )
    work = WorkDir.at(tmp_path / "work")
    calib.save(work.calibration)
    return work


def test_run_relight_writes_images_and_error_vs_all(tmp_path):
    from lightstage.frames import read_exr, write_exr

    work = _work_with_calibration(tmp_path)
    write_exr(tmp_path / "env.exr", _sky(64, 128).astype(np.float32), half=False)
    config = RelightConfig.from_dict(
        {"envmap": str(tmp_path / "env.exr"), "lights": "4,32,all", "out": str(tmp_path / "out")}
    )
    summary = run_relight(work, config, progress=False, model=FakeSphere())
    assert summary["light_distance_m"] == pytest.approx(1.5)
    assert summary["olat_factor"] == pytest.approx(2.25)
    res = summary["views"]["000_cam00"]["results"]
    assert res["4"]["vs_all"]["relative_l2"] > res["32"]["vs_all"]["relative_l2"]
    assert res["32"]["vs_all"]["psnr_tonemapped_db"] > res["4"]["vs_all"]["psnr_tonemapped_db"]
    out = tmp_path / "out"
    for f in ("000_cam00_k004.exr", "000_cam00_k032.png", "000_cam00_all.exr", "envmap_lights_k032.png"):
        assert (out / f).is_file(), f
    assert read_exr(out / "000_cam00_all.exr").shape == (24, 32, 3)
    saved = json.loads((out / "relight.json").read_text())
    assert saved["exposure"] > 0 and "vs_all" in saved["views"]["000_cam00"]["results"]["4"]
    with pytest.raises(LightstageError, match="unknown key"):
        RelightConfig.from_dict({"envmapp": "x"})
    with pytest.raises(LightstageError, match="rotate_deg"):
        RelightConfig.from_dict({"rotate_deg": "ten"})
    assert RelightConfig.from_dict({"lights": 16, "cameras": ["orbit"]}).lights == 16


def test_camera_and_light_specs(tmp_path):
    work = _work_with_calibration(tmp_path)
    scene = load_scene_info(work)
    model = FakeSphere()
    cal = parse_camera("000/cam00", scene, model)
    assert (cal.camera.width, cal.camera.height) == (32, 24)
    orb = parse_camera("orbit:az=90,elev=0,dist=2,fov=40,size=64x48", scene, model).camera
    np.testing.assert_allclose(camera_center(orb.R, orb.t), model.centre + [0, 2, 0], atol=1e-12)
    K, R, t = cal.camera.K, cal.camera.R, cal.camera.t
    spec = "K={},{},{},{};R={};t={};size=32x24".format(
        K[0, 0],
        K[1, 1],
        K[0, 2],
        K[1, 2],
        ",".join(str(float(v)) for v in R.ravel()),
        ",".join(str(float(v)) for v in t),
    )
    exp = parse_camera(spec, scene, model).camera
    np.testing.assert_allclose(exp.K, K) and np.testing.assert_allclose(exp.R, R)
    (tmp_path / "cam.json").write_text(
        json.dumps({"K": K.tolist(), "R": R.tolist(), "t": t.tolist(), "width": 32, "height": 24})
    )
    np.testing.assert_allclose(parse_camera(str(tmp_path / "cam.json"), scene, model).camera.t, t)
    (tmp_path / "cams").mkdir()
    (tmp_path / "cams" / "c.json").write_text((tmp_path / "cam.json").read_text())
    assert parse_camera(str(tmp_path / "cams" / "c.json"), scene, model).name == "c"
    for bad in ("000/cam99", "orbit:zoom=2", "K=1,2;R=1;t=0;size=3x3", "nonsense"):
        with pytest.raises(LightstageError):
            parse_camera(bad, scene, model)
    # lights
    assert np.allclose(parse_light("dir:0,0,2", scene).direction, [0, 0, 1])
    assert np.allclose(parse_light("azel:90,0", scene).direction, [0, 1, 0], atol=1e-12)
    stage = parse_light("000/1", scene)
    assert np.allclose(stage.direction, [0, 0, 1]) and stage.scale == 1.0
    near = parse_light("pos:0,0,0.75", scene)  # half the capture distance: 4x the irradiance
    assert np.allclose(near.direction, [0, 0, 1]) and near.scale == pytest.approx(4.0)
    assert parse_light("pos:0,0,3,2", scene).scale == pytest.approx(0.5)
    for bad in ("dir:0,0,0", "000/7", "pos:1,2", "sun"):
        with pytest.raises(LightstageError):
            parse_light(bad, scene)
    # orbit rotation keeps the distance to the centre and turns the view about +z
    rot = rotate_camera_about_z(orb, 90.0, model.centre)
    np.testing.assert_allclose(camera_center(rot.R, rot.t), model.centre + [-2, 0, 0], atol=1e-12)


def test_run_render_single_and_orbit(tmp_path):
    work = _work_with_calibration(tmp_path)
    model = FakeSphere()
    single = run_render(
        work,
        RenderConfig(camera="000/cam00", light="000/1", out=str(tmp_path / "r1")),
        progress=False,
        model=model,
    )
    assert single["frames"] == 1
    from lightstage.frames import read_exr

    img = read_exr(tmp_path / "r1" / "000_cam00_light000_001.exr").astype(np.float32)
    ref = model.image_from_camera(
        parse_camera("000/cam00", load_scene_info(work), model).camera, np.array([0, 0, 1.0])
    )
    np.testing.assert_allclose(img, ref, rtol=1e-3, atol=1e-3)  # float16 on disk
    config = RenderConfig.from_dict(
        {"camera": "orbit:size=32x24", "light": "dir:1,0,1", "orbit": 6, "out": str(tmp_path / "r2")}
    )
    summary = run_render(work, config, progress=False, model=model)
    out = tmp_path / "r2"
    assert (out / "orbit.mp4").stat().st_size > 0 and (out / "orbit_strip.png").is_file()
    assert len(list((out / "frames").glob("*.exr"))) == 6
    import cv2

    cap = cv2.VideoCapture(str(out / "orbit.mp4"))
    count = 0
    while cap.read()[0]:
        count += 1
    assert count == 6
    assert summary["exposure"] > 0


@pytest.fixture(scope="module")
def trained_work(tmp_path_factory):
    """A work dir with a (barely) trained tiny checkpoint of the model package's synthetic sphere."""
    pytest.importorskip("lightstage.training.inference")  # the model package's loader (load_trained)
    pytest.importorskip("lightstage.training.trainer")
    from support.synthetic import SyntheticSphere

    from lightstage.training.config import load_config
    from lightstage.training.trainer import fit

    work = WorkDir.at(tmp_path_factory.mktemp("trained") / "work")
    cfg = load_config(
        "tiny", {"optim": {"steps": 3, "batch_rays": 64}, "checkpoint_every": 3, "eval": {"stats_batches": 1}}
    )
    sphere = SyntheticSphere(batch_size=64)
    fit(cfg, sphere, work.train_dir, sphere.centre, sphere.scale, progress=False)
    return work


@pytest.mark.slow
def test_cli_relight_render_mesh_on_a_trained_checkpoint(trained_work, tmp_path, capsys):
    from lightstage.frames import read_exr, write_exr
    from lightstage.pipelines.cli import main
    from lightstage.training.inference import load_trained
    from lightstage.training.mesh import density_grid, read_ply

    work = str(trained_work.root)
    write_exr(tmp_path / "env.exr", _sky(32, 64).astype(np.float32), half=False)
    rc = main(
        ["relight", work, "--envmap", str(tmp_path / "env.exr"), "--lights", "2,all", "--resolution", "8x4",
         "--camera", "orbit:size=16x12", "--rotate-deg", "30", "--out", str(tmp_path / "relit")]
    )  # fmt: skip
    assert rc == 0
    summary = json.loads((tmp_path / "relit" / "relight.json").read_text())
    res = summary["views"]["orbit_az0_el20"]["results"]
    assert res["all"]["lights"] == 32 and "relative_l2" in res["2"]["vs_all"]
    assert summary["olat_factor"] == pytest.approx(2.25)  # no calibration: the paper stage's 1.5 m
    assert np.all(np.isfinite(read_exr(tmp_path / "relit" / "orbit_az0_el20_all.exr")))

    rc = main(["render", work, "--camera", "orbit:size=16x12", "--light", "azel:30,45", "--orbit", "3",
               "--out", str(tmp_path / "orbit")])  # fmt: skip
    assert (
        rc == 0
        and (tmp_path / "orbit" / "orbit.mp4").is_file()
        and (tmp_path / "orbit" / "orbit_strip.png").is_file()
    )

    model = load_trained(trained_work)
    grid = density_grid(model, 12, progress=False)
    capsys.readouterr()
    assert (
        main(["mesh", work, "--resolution", "12", "--threshold", "1e30", "--out", str(tmp_path / "m.ply")])
        == 2
    )
    assert "outside the grid's range" in capsys.readouterr().err
    level = float(np.quantile(grid, 0.9))
    if level > grid.min():
        rc = main(
            ["mesh", work, "--resolution", "12", "--threshold", repr(level), "--out", str(tmp_path / "m.ply")]
        )
        assert rc == 0
        v, f = read_ply(tmp_path / "m.ply")
        lo, hi = model.centre - model.scale, model.centre + model.scale
        assert (
            len(f) > 0 and np.all(v >= lo - 1e-4) and np.all(v <= hi + 1e-4)
        )  # world units, inside the bounds
    # bad input is one line, exit 2
    assert (
        main(["relight", work, "--envmap", str(tmp_path / "missing.exr"), "--out", str(tmp_path / "x")]) == 2
    )
    assert (
        main(["render", work, "--camera", "000/cam00", "--light", "dir:0,0,1", "--out", str(tmp_path / "x")])
        == 2
    )
    assert "no calibration" in capsys.readouterr().err


def test_hdr_outputs_keep_values_beyond_half_range(tmp_path):
    from lightstage.exr_header import read_exr_header
    from lightstage.frames import read_exr
    from lightstage.training.relight import write_hdr

    img = np.full((4, 5, 3), 1.0e6, np.float32)
    write_hdr(tmp_path / "big.exr", img)
    assert read_exr_header(tmp_path / "big.exr").dtype == "float"
    np.testing.assert_array_equal(read_exr(tmp_path / "big.exr"), img)
    write_hdr(tmp_path / "small.exr", img * 1e-6)
    assert read_exr_header(tmp_path / "small.exr").dtype == "half"


def test_repeated_cameras_get_distinct_outputs(tmp_path):
    from lightstage.frames import write_exr

    write_exr(tmp_path / "env.exr", _sky().astype(np.float32), half=False)
    config = RelightConfig(
        envmap=str(tmp_path / "env.exr"),
        lights="8",
        cameras=["orbit:size=8x6", "orbit:size=8x6"],
        out=str(tmp_path / "o"),
    )
    summary = run_relight(WorkDir.at(tmp_path / "w"), config, progress=False, model=FakeSphere())
    assert sorted(summary["views"]) == ["orbit_az0_el20", "orbit_az0_el20_2"]
    assert (tmp_path / "o" / "orbit_az0_el20_2_k008.exr").is_file()
