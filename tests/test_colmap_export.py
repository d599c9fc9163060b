"""The COLMAP export opens as it should: pycolmap loads it, every image name resolves to a file of the camera's
size, the rig is one rig of the real sensors with one frame per group, and SfM points reproject within 1 px
of their observations (outliers left out)."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
from support.fixtures import make_synthetic_work

from lightstage.calibration.export import (
    build_colmap_model,
    colmap_image_name,
    sfm_tracks,
    transforms_dict,
    write_colmap_model,
    write_transforms,
)
from lightstage.calibration.register import Similarity
from lightstage.cameras import opengl_c2w_to_opencv, rotation_axis_angle
from lightstage.records.calibration import Calibration
from lightstage.workdir import DOWNSCALE

pycolmap = pytest.importorskip("pycolmap")


@pytest.fixture
def work(tmp_path):
    """A synthetic work dir (4 cameras x 3 groups) with well-lit PNGs beside its masks."""
    work, _ = make_synthetic_work(tmp_path, num_cameras=4, num_lights=2, num_groups=3)
    calib = Calibration.load(work.calibration)
    for v in calib.views:
        mask = cv2.imread(str(work.mask(v)), cv2.IMREAD_GRAYSCALE)
        cv2.imwrite(str(work.wellit(v)), np.dstack([mask // 2] * 3))
    return work


def _fake_sfm(calib: Calibration, sim: Similarity, factor: int, rng, outlier: bool = True):
    """A pycolmap reconstruction in SfM units (world = sim(sfm)) whose keypoints, at raw / factor, are the
    projections of random points near the origin plus 0.05 px noise; one observation 6 px off."""
    world_pts = rng.uniform(-0.08, 0.08, size=(30, 3))
    inv = sim.inverse()
    rec = pycolmap.Reconstruction()
    kp: dict[str, list] = {}
    tracks = []
    for X in world_pts:
        track = []
        for v, vc in sorted(calib.views.items()):
            cam = vc.camera(1)  # raw
            xc = cam.R @ X + cam.t
            uv = (cam.K @ xc)[:2] / xc[2] / factor + rng.normal(0, 0.05, 2)
            name = colmap_image_name(v.group, v.camera)
            track.append((name, len(kp.setdefault(name, []))))
            kp[name].append(uv)
        tracks.append(track)
    if outlier:
        name, idx = tracks[0][0]
        kp[name][idx] = kp[name][idx] + 6.0 / DOWNSCALE * factor
    cams = sorted({v.camera for v in calib.views})
    for i in range(1, len(cams) + 1):
        cam = pycolmap.Camera.create_from_model_name(i, "PINHOLE", 100.0, 64, 48)
        rec.add_camera_with_trivial_rig(cam)
    ids = {}
    for i, (v, _vc) in enumerate(sorted(calib.views.items()), start=1):
        name = colmap_image_name(v.group, v.camera)
        ids[name] = i
        im = pycolmap.Image(
            name=name, camera_id=cams.index(v.camera) + 1, image_id=i, keypoints=np.asarray(kp[name])
        )
        rec.add_image_with_trivial_frame(im, pycolmap.Rigid3d())
    for X, track in zip(world_pts, tracks, strict=True):
        t = pycolmap.Track()
        for name, idx in track:
            t.add_element(ids[name], idx)
        rec.add_point3D(inv.apply(X[None])[0], t, np.array([200, 100, 50], np.uint8))
    return rec


def _reprojection_errors(model) -> np.ndarray:
    errs = []
    for image in model.images.values():
        T = image.cam_from_world()
        R, t = T.rotation.matrix(), np.asarray(T.translation)
        for p in image.points2D:
            if p.has_point3D():
                xc = R @ model.points3D[p.point3D_id].xyz + t
                errs.append(np.linalg.norm(np.asarray(image.camera.img_from_cam(xc[None])).ravel() - p.xy))
    return np.asarray(errs)


def test_model_names_files_of_the_camera_size_one_rig_and_tracks(work):
    calib = Calibration.load(work.calibration)
    rng = np.random.default_rng(1)
    sim = Similarity(2.7, rotation_axis_angle(np.array([0.3, -0.5, 0.8]), 0.7), np.array([0.2, -0.1, 0.4]))
    tracks = sfm_tracks(_fake_sfm(calib, sim, 2, rng), sim, 2 / DOWNSCALE)
    out = work.calibration_dir / "colmap"
    stats = write_colmap_model(calib, out, tracks, work)
    model = pycolmap.Reconstruction(str(out))

    assert model.num_images() == len(calib.views) == stats["images_written"] == 12
    for image in model.images.values():
        path = out / "images" / image.name
        img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        assert img is not None, path
        assert img.shape[1::-1] == (image.camera.width, image.camera.height)
        assert (out / "masks" / f"{image.name}.png").is_file()
    # one rig of the 4 real sensors, one frame per group, poses as calibrated
    assert model.num_rigs() == 1 and next(iter(model.rigs.values())).num_sensors() == 4
    assert model.num_frames() == 3
    for image in model.images.values():
        cam, group = image.name[:-4].split("/")
        vc = next(c for v, c in calib.views.items() if (v.camera, v.group) == (cam, group))
        T = image.cam_from_world()
        assert np.allclose(T.rotation.matrix(), vc.R, atol=1e-9) and np.allclose(
            T.translation, vc.t, atol=1e-9
        )
    # observations and tracks: every point seen in all 12 views, the planted 6 px outlier left out
    assert model.num_points3D() == 30 and stats["dropped_observations"] == 1
    assert model.compute_num_observations() == 30 * 12 - 1
    errs = _reprojection_errors(model)
    assert errs.size == 359 and errs.max() < 1.0, errs.max()
    assert 0 < model.compute_mean_reprojection_error() < 1.0
    assert (out / "points3D.ply").is_file()


def test_nominal_export_has_cameras_only_and_trivial_rigs_when_not_rigid(work):
    calib = Calibration.load(work.calibration)
    rec, stats = build_colmap_model(calib)
    assert rec.num_points3D() == 0 and stats["observations"] == 0 and "one rig of 4 sensors" in stats["rig"]
    # a camera moved in one group only: no longer one rigid rig, so one trivial rig per camera
    v = sorted(calib.views)[5]
    moved = dict(calib.views)
    moved[v] = type(calib.views[v])(calib.views[v].K_raw, calib.views[v].R, calib.views[v].t + 0.01, 192, 128)
    rec, stats = build_colmap_model(Calibration(calib.method, moved, calib.light_positions, calib.axis, {}))
    assert rec.num_rigs() == 4 and "one-sensor rigs" in stats["rig"]


def test_a_wellit_image_of_another_size_is_one_error_naming_it(work):
    calib = Calibration.load(work.calibration)
    v = sorted(calib.views)[0]
    cv2.imwrite(str(work.wellit(v)), np.zeros((10, 12, 3), np.uint8))
    from lightstage.errors import LightstageError

    with pytest.raises(LightstageError, match=r"wellit.png: 12x10, but the camera"):
        write_colmap_model(calib, work.calibration_dir / "colmap", None, work)


def test_transforms_masks_applied_transform_and_split_lists(work):
    from lightstage.dataset.split import SplitConfig, run_split

    calib = Calibration.load(work.calibration)
    d = transforms_dict(calib, work, work.calibration_dir)
    assert "train_filenames" not in d  # no split yet
    run_split(
        work, SplitConfig.from_dict({"protocol": {"base": "paper", "cameras": {"test": 1}}}), progress=False
    )
    path = write_transforms(calib, work.calibration_dir / "transforms.json", work)
    d = json.loads(path.read_text())
    assert np.allclose(d["applied_transform"], np.eye(4)[:3])
    for f in d["frames"]:
        assert (path.parent / f["mask_path"]).is_file() and (path.parent / f["file_path"]).is_file()
        R, t = opengl_c2w_to_opencv(np.array(f["transform_matrix"]))
        vc = calib.views[next(v for v in calib.views if (v.group, v.camera) == (f["group"], f["camera"]))]
        assert np.allclose(R, vc.R, atol=1e-12) and np.allclose(t, vc.t, atol=1e-12)
    assert len(d["train_filenames"]) == 9 and len(d["test_filenames"]) == 3 == len(d["val_filenames"])
    assert not set(d["train_filenames"]) & set(d["test_filenames"])
    assert all("cam03" in n for n in d["test_filenames"])
