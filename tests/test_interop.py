"""Round trip through the per-frame point-light OLAT format: a simulated `tiny` capture run to split, exported,
imported into a fresh work directory: the same cameras, lights, images (to float precision) and split; the
exported fields follow the conventions the relighting codes' loaders read; and a model trained on the
imported copy (`lightstage run WORK/import.yaml --from split`) evaluates like one trained on the original."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import yaml

from lightstage.ids import ViewId
from lightstage.records.calibration import Calibration
from lightstage.records.processed import read_mask, read_processed
from lightstage.records.split import load_split
from lightstage.workdir import DOWNSCALE, WorkDir

# every non-test light trains (tiny: 12 lights, 1 test light, 1 test camera of 4)
SPLIT = {"protocol": {"base": "paper", "lights": {"train": "rest"}}}
SECTIONS = {"cluster": {"workers": 0}, "calibrate": {"method": "nominal"}, "split": SPLIT}
MICRO_TRAIN = {
    "config": "tiny",
    "optim": {"steps": 60, "batch_rays": 128, "warmup_steps": 2},
    "model": {
        "mlp": {"depth": 2, "width": 16, "skip": 1, "head_width": 8, "pos_freqs": 2},
        "n_coarse": 8,
        "n_fine": 8,
    },
    "eval": {"stats_batches": 2},
    "checkpoint_every": 60,
}
SHARD = {"foreground_fraction": 0.5, "rays_per_shard": 8192, "workers": 1}


@pytest.fixture(scope="module")
def roundtrip(tiny_capture: Path, tmp_path_factory):
    """(original WORK run to split, the olat export, the imported WORK)."""
    from lightstage.interop.exports import export_work
    from lightstage.interop.ingest import write_work
    from lightstage.interop.olat import read_olat
    from lightstage.pipelines.config import PipelineConfig
    from lightstage.pipelines.runner import run_pipeline

    root = tmp_path_factory.mktemp("interop")
    work = WorkDir.at(root / "work")
    config = PipelineConfig.from_dict(SECTIONS, "roundtrip.yaml")
    run_pipeline(work, config, capture=tiny_capture, to_stage="split", progress=False, log=lambda m: None)
    export_work(work, "olat", root / "olat")
    imported = WorkDir.at(root / "imported")
    write_work(read_olat(root / "olat"), imported)
    return work, root / "olat", imported


@pytest.mark.slow  # the module fixture runs the tiny capture to split (~45 s on 2 busy cores)
def test_same_cameras_lights_images_and_split(roundtrip):
    work, _, imported = roundtrip
    ca, cb = Calibration.load(work.calibration), Calibration.load(imported.calibration)
    sa, sb = load_split(work.split), load_split(imported.split)
    assert set(sa.train.frames()) == set(sb.train.frames()) and set(sa.test.frames()) == set(sb.test.frames())
    assert sb.counts()["train"] == sa.counts()["train"] and sb.counts()["test"] == sa.counts()["test"]
    assert set(cb.views) == {ViewId(f.group, f.camera) for f in [*sa.train.frames(), *sa.test.frames()]}
    for v, b in cb.views.items():
        a = ca.views[v]
        assert np.abs(a.R - b.R).max() < 1e-12 and np.abs(a.t - b.t).max() < 1e-12
        assert np.array_equal(a.K_raw, b.K_raw) and (a.width_raw, a.height_raw) == (b.width_raw, b.height_raw)
    for g, p in ca.light_positions.items():
        assert np.array_equal(p, cb.light_positions[g])
    assert ca.yaws_deg == cb.yaws_deg and np.array_equal(ca.scene_centre, cb.scene_centre)
    for f in [*sa.train.frames(), *sa.test.frames()]:
        (ra, ka), (rb, kb) = read_processed(work.frame(f)), read_processed(imported.frame(f))
        assert np.array_equal(ra, rb) and np.array_equal(ka, kb), f
    for v in cb.views:
        assert np.array_equal(read_mask(work.mask(v)), read_mask(imported.mask(v)))
    report = json.loads(imported.report("import").read_text())
    assert report["frames"] == sa.counts()["train"] + sa.counts()["test"]


@pytest.mark.slow
def test_exported_fields_follow_the_loaders_conventions(roundtrip):
    """What NRHints / GS^3 / nerfstudio-style loaders compute from the file is our camera and light."""
    from lightstage.frames import read_exr

    work, out, _ = roundtrip
    calib = Calibration.load(work.calibration)
    doc = json.loads((out / "transforms_test.json").read_text())
    assert len(doc["camera_intrinsics"]) == 4 and doc["camera_near"] < doc["camera_far"]
    for fr in doc["frames"][:5]:
        ids = fr["lightstage"]
        vc = calib.views[ViewId(ids["group"], ids["camera"])]
        # GS^3 (scene/dataset_readers.py): flip y and z of the OpenGL c2w, invert, R stored transposed
        c2w = np.array(fr["transform_matrix"])
        c2w[:3, 1:3] *= -1
        w2c = np.linalg.inv(c2w)
        assert np.allclose(w2c[:3, :3], vc.R, atol=1e-12) and np.allclose(w2c[:3, 3], vc.t, atol=1e-12)
        cx, cy, fx, fy = fr["camera_intrinsics"]
        K = vc.camera(DOWNSCALE).K
        assert (fx, fy, cx, cy) == (K[0, 0], K[1, 1], K[0, 2], K[1, 2])
        assert np.array_equal(fr["pl_pos"], calib.light_positions[ids["group"]][ids["light"]])
        img = read_exr(out / (fr["file_path"] + fr["file_ext"]), channels="RGBA")
        assert img.dtype == np.float16 and img.shape[:2] == (fr["h"], fr["w"])
        mask = read_mask(out / fr["mask_path"])
        assert np.array_equal(img[..., 3] > 0.5, mask)


@pytest.mark.slow
def test_a_model_trained_on_the_imported_copy_evaluates_like_the_original(roundtrip, tmp_path):
    from lightstage.pipelines.cli import main
    from lightstage.pipelines.config import PipelineConfig
    from lightstage.pipelines.runner import run_pipeline

    work, _, imported = roundtrip
    config = PipelineConfig.from_dict({**SECTIONS, "shard": SHARD, "train": MICRO_TRAIN}, "original.yaml")
    run_pipeline(work, config, from_stage="bounds", progress=False, log=lambda m: None)
    # the imported copy through the CLI and the import's own pipeline config (a lab adds its training section)
    cfg_path = imported.root / "import.yaml"
    cfg = yaml.safe_load(cfg_path.read_text())
    cfg.update(cluster={"workers": 0}, shard=SHARD, train=MICRO_TRAIN)
    cfg_path.write_text(yaml.safe_dump(cfg))
    assert main(["run", str(cfg_path), "--from", "split", "-q"]) == 0
    assert load_split(imported.split).to_dict()["train"] == load_split(work.split).to_dict()["train"]
    a = json.loads(work.report("eval").read_text())["mean"]
    b = json.loads(imported.report("eval").read_text())["mean"]
    assert abs(a["psnr"] - b["psnr"]) < 0.1, (a["psnr"], b["psnr"])
    assert b["psnr"] > b["baseline_psnr"]  # it learnt something
