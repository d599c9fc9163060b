"""Fixtures written here in the exact file layouts of the formats (a few frames each) import without error, the
split they give reruns identically through the split stage, and malformed variants (missing images, sizes
that differ, lights missing, bad JSON) are one `lightstage: error:` line naming the file. Plus the nerfstudio
and COLMAP exports of `lightstage export`."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from lightstage.cameras import look_at, opencv_to_opengl_c2w
from lightstage.ids import ViewId
from lightstage.pipelines.cli import main
from lightstage.records.calibration import Calibration
from lightstage.records.processed import read_mask, read_processed
from lightstage.records.split import load_split
from lightstage.workdir import WorkDir

W, H = 24, 16


def _pose(az_deg: float, dist: float = 2.0):
    """(R, t) world-to-camera (OpenCV) of a camera at azimuth `az_deg`, 20 deg up, looking at the origin."""
    a, e = np.deg2rad(az_deg), np.deg2rad(20.0)
    eye = dist * np.array([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)])
    return look_at(eye, np.zeros(3), np.array([0.0, 0.0, 1.0]))


def _disc(value: float = 0.5) -> np.ndarray:
    """(H, W) disc mask and an RGB image: `value` inside (one pixel full scale), 0.1 outside."""
    yy, xx = np.mgrid[:H, :W]
    mask = (xx - W / 2) ** 2 + (yy - H / 2) ** 2 < 36
    rgb = np.where(mask[..., None], value, 0.1) * np.ones(3)
    rgb[H // 2, W // 2] = 1.0
    return mask, rgb


def write_nerf_olat(root: Path) -> dict:
    """The NRHints / GS^3 layout: transforms_{train,test}.json with one top-level camera_intrinsics, frames
    of file_path (no extension, PNG by default), OpenGL transform_matrix and pl_pos; RGBA PNGs whose alpha is
    the mask. Train: cameras at 0 and 90 deg x lights 0, 1; test: the camera at 200 deg under light 2."""
    root.mkdir(parents=True)
    lights = [[1.5, 0.0, 1.0], [0.0, 1.5, 1.0], [-1.0, -1.0, 1.2]]
    f = 30.0
    parts = {"train": [(0, 0), (0, 1), (90, 0), (90, 1)], "test": [(200, 2)]}
    mask, rgb = _disc()
    for part, frames in parts.items():
        entries = []
        for k, (az, light) in enumerate(frames):
            R, t = _pose(az)
            name = f"{part}/r_{k:03d}"
            (root / part).mkdir(exist_ok=True)
            png = np.dstack([rgb * (0.5 + 0.2 * light), mask]) * 255
            png[H // 2, W // 2, :3] = 255  # one clipped pixel
            cv2.imwrite(str(root / f"{name}.png"), np.round(png).astype(np.uint8)[..., [2, 1, 0, 3]])
            entries.append(
                {
                    "file_path": name,
                    "transform_matrix": opencv_to_opengl_c2w(R, t).tolist(),
                    "pl_pos": lights[light],
                }
            )
        doc = {
            "camera_intrinsics": [W / 2, H / 2, f, f],
            "camera_near": 0.5,
            "camera_far": 4.0,
            "frames": entries,
        }
        (root / f"transforms_{part}.json").write_text(json.dumps(doc))
    return {"lights": lights, "f": f}


def write_openillumination(base: Path, cameras=("CA2", "CA4", "NA3"), test=("NA3",), lights=4) -> Path:
    """OpenIllumination's layout under BASE/OpenIllumination: light_pos.npy (global table), and
    OLAT/obj_01_ball/{output/transforms_{train,test}.json (frames keyed by camera), output/obj_masks/CAM.png,
    Lights/NNN/raw_undistorted/CAM.JPG}."""
    dataset = base / "OpenIllumination"
    obj = dataset / "OLAT" / "obj_01_ball"
    (obj / "output" / "obj_masks").mkdir(parents=True)
    table = np.array([[np.cos(a), np.sin(a), 0.8] for a in np.linspace(0, 2 * np.pi, 6, endpoint=False)])
    np.save(dataset / "light_pos.npy", table)
    mask, rgb = _disc(0.6)
    fov = 2 * np.arctan(0.5 * W / 30.0)
    docs = {"train": {}, "test": {}}
    for i, cam in enumerate(cameras):
        R, t = _pose(120.0 * i)
        docs["test" if cam in test else "train"][cam] = {
            "transform_matrix": opencv_to_opengl_c2w(R, t).tolist(),
            "camera_angle_x": fov,
        }
        cv2.imwrite(str(obj / "output" / "obj_masks" / f"{cam}.png"), mask.astype(np.uint8) * 255)
        for lt in range(lights):
            d = obj / "Lights" / f"{lt:03d}" / "raw_undistorted"
            d.mkdir(parents=True, exist_ok=True)
            cv2.imwrite(
                str(d / f"{cam}.JPG"), np.round(rgb * 255).astype(np.uint8), [cv2.IMWRITE_JPEG_QUALITY, 100]
            )
    for part, frames in docs.items():
        (obj / "output" / f"transforms_{part}.json").write_text(json.dumps({"frames": frames}))
    return obj


def _import(fmt: str, path: Path, work: Path, *extra: str) -> int:
    return main(["import", fmt, str(path), "--work", str(work), "-q", *extra])


def test_nerf_style_olat_fixture_imports(tmp_path, capsys):
    meta = write_nerf_olat(tmp_path / "nr")
    assert _import("olat", tmp_path / "nr", tmp_path / "work") == 0
    work = WorkDir.at(tmp_path / "work")
    calib = Calibration.load(work.calibration)
    split = load_split(work.split)
    assert split.counts()["train"] == 4 and split.counts()["test"] == 1
    assert len(calib.views) == 3 and len(calib.light_positions["000"]) == 3
    assert np.allclose(calib.light_positions["000"], meta["lights"])
    # cameras found by their values: the first is the 0-degree camera, K at raw = 4 x the file's
    v0 = sorted(calib.views)[0]
    R, t = _pose(0)
    assert np.allclose(calib.views[v0].R, R, atol=1e-12) and np.allclose(calib.views[v0].t, t, atol=1e-12)
    assert np.allclose(calib.views[v0].K_raw[0], [4 * meta["f"], 0, 4 * W / 2])
    # sRGB PNGs linearised, full-scale pixels flagged, masks from alpha
    f = next(iter(split.train.frames()))
    rgb, sat = read_processed(work.frame(f), (W, H))
    assert sat[H // 2, W // 2] and sat.sum() == 1
    mask = read_mask(work.mask(ViewId(f.group, f.camera)))
    expected = ((np.round(0.5 * 0.5 * 255) / 255 + 0.055) / 1.055) ** 2.4
    assert mask[H // 2, W // 2 + 2] and np.isclose(rgb[H // 2, W // 2 + 2, 0], expected, rtol=1e-3)
    assert "--from split" in capsys.readouterr().out


def test_openillumination_fixture_imports_and_its_split_reruns_identically(tmp_path):
    from lightstage.pipelines.config import load_pipeline_config
    from lightstage.pipelines.runner import run_pipeline

    obj = write_openillumination(tmp_path)
    assert _import("openillumination", obj, tmp_path / "work") == 0
    work = WorkDir.at(tmp_path / "work")
    calib = Calibration.load(work.calibration)
    split = load_split(work.split)
    assert split.test.cameras() == {"NA3"} and split.train.cameras() == {"CA2", "CA4"}
    assert len(split.test.lights()) == 1 and len(split.train.lights()) == 3  # lights split too (unseen tests)
    assert split.counts()["train"] == 6 and split.counts()["test"] == 1
    table = np.load(tmp_path / "OpenIllumination" / "light_pos.npy")
    assert np.array_equal(calib.light_positions["000"], table[:4])
    K = calib.views[sorted(calib.views)[0]].camera(4).K
    assert np.allclose(K, [[30.0, 0, W / 2], [0, 30.0, H / 2], [0, 0, 1]])
    before = json.loads(work.split.read_text())
    config = load_pipeline_config(work.root / "import.yaml").with_cluster(workers=0)
    run_pipeline(work, config, only="split", progress=False, log=lambda m: None)
    after = json.loads(work.split.read_text())
    assert after["train"] == before["train"] and after["test"] == before["test"]


def _one_error_line(capsys) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("lightstage: error: "), err
    return err[0]


def test_malformed_olat_variants_are_one_line_naming_the_file(tmp_path, capsys):
    src = tmp_path / "nr"
    write_nerf_olat(src)

    def variant(name: str) -> Path:
        d = tmp_path / name
        shutil.copytree(src, d)
        return d

    d = variant("missing_image")
    (d / "train" / "r_001.png").unlink()
    assert _import("olat", d, tmp_path / "w1") == 2
    assert "r_001.png: missing (transforms_train.json frame 1)" in _one_error_line(capsys)

    d = variant("no_light")
    doc = json.loads((d / "transforms_test.json").read_text())
    del doc["frames"][0]["pl_pos"]
    (d / "transforms_test.json").write_text(json.dumps(doc))
    assert _import("olat", d, tmp_path / "w2") == 2
    assert "transforms_test.json: frame 0 has no pl_pos" in _one_error_line(capsys)

    d = variant("sizes")
    cv2.imwrite(str(d / "train" / "r_002.png"), np.zeros((H, W + 2, 4), np.uint8))
    assert _import("olat", d, tmp_path / "w3") == 2
    assert f"r_002.png: {W + 2}x{H}, but" in _one_error_line(capsys)

    d = variant("json")
    (d / "transforms_train.json").write_text("{not json")
    assert _import("olat", d, tmp_path / "w4") == 2
    assert "transforms_train.json: invalid JSON" in _one_error_line(capsys)

    d = variant("no_test")
    (d / "transforms_test.json").unlink()
    assert _import("olat", d, tmp_path / "w5") == 2
    assert "transforms_test.json: missing" in _one_error_line(capsys)

    assert _import("olat", src, tmp_path / "ok") == 0
    assert _import("olat", src, tmp_path / "ok") == 2  # never over an existing work directory
    assert "import into a new one" in _one_error_line(capsys)


def test_malformed_openillumination_variants_are_one_line_naming_the_file(tmp_path, capsys):
    def variant(name: str) -> Path:
        return write_openillumination(tmp_path / name)

    obj = variant("no_table")
    (obj.parent.parent / "light_pos.npy").unlink()
    assert _import("openillumination", obj, tmp_path / "w1") == 2
    assert "light_pos.npy: missing" in _one_error_line(capsys)

    obj = variant("extra_light")
    shutil.copytree(obj / "Lights" / "000", obj / "Lights" / "009")
    assert _import("openillumination", obj, tmp_path / "w2") == 2
    assert "light_pos.npy: 6 light positions, but" in _one_error_line(capsys)

    obj = variant("missing_image")
    (obj / "Lights" / "001" / "raw_undistorted" / "CA4.JPG").unlink()
    assert _import("openillumination", obj, tmp_path / "w3") == 2
    assert "Lights/001/raw_undistorted/CA4.JPG: missing (camera CA4 under light 001)" in _one_error_line(
        capsys
    )

    obj = variant("missing_mask")
    (obj / "output" / "obj_masks" / "CA2.png").unlink()
    assert _import("openillumination", obj, tmp_path / "w4") == 2
    assert "obj_masks/CA2.png: missing" in _one_error_line(capsys)

    obj = variant("sizes")
    img = obj / "Lights" / "001" / "raw_undistorted" / "CA2.JPG"
    cv2.imwrite(str(img), np.zeros((H + 4, W, 3), np.uint8))
    assert _import("openillumination", obj, tmp_path / "w5") == 2
    assert "sizes differ" in _one_error_line(capsys)


def test_export_nerfstudio_and_colmap_are_self_contained(tmp_path, capsys):
    from support.fixtures import make_synthetic_work

    from lightstage.calibration.export import write_colmap_model
    from lightstage.dataset.split import SplitConfig, run_split

    work, _ = make_synthetic_work(tmp_path, num_cameras=4, num_lights=2, num_groups=2)
    calib = Calibration.load(work.calibration)
    for v in calib.views:
        cv2.imwrite(str(work.wellit(v)), np.dstack([cv2.imread(str(work.mask(v)), cv2.IMREAD_GRAYSCALE)] * 3))
    run_split(
        work, SplitConfig.from_dict({"protocol": {"base": "paper", "cameras": {"test": 1}}}), progress=False
    )
    assert (
        main(["export", str(work.root), "--format", "nerfstudio", "--out", str(tmp_path / "ns"), "-q"]) == 0
    )
    d = json.loads((tmp_path / "ns" / "transforms.json").read_text())
    for f in d["frames"]:
        assert (tmp_path / "ns" / f["file_path"]).is_file() and (tmp_path / "ns" / f["mask_path"]).is_file()
    assert set(d["train_filenames"]) | set(d["test_filenames"]) == {f["file_path"] for f in d["frames"]}
    assert main(["export", str(work.root), "--format", "colmap", "--out", str(tmp_path / "cm")]) == 2
    assert "no COLMAP model" in _one_error_line(capsys)
    write_colmap_model(calib, work.calibration_dir / "colmap", None, work)
    assert main(["export", str(work.root), "--format", "colmap", "--out", str(tmp_path / "cm"), "-q"]) == 0
    pycolmap = pytest.importorskip("pycolmap")
    model = pycolmap.Reconstruction(str(tmp_path / "cm"))
    assert all((tmp_path / "cm" / "images" / im.name).is_file() for im in model.images.values())
    assert main(["export", str(work.root), "--format", "olat", "--out", str(work.root / "x")]) == 2
    assert "outside the work directory" in _one_error_line(capsys)
