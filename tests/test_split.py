"""Splits as data: the paper protocol on the paper preset, planted overlaps, adaptation, rejected frames."""

from __future__ import annotations

import json

import numpy as np
import pytest

from lightstage.capture.presets import make_stage, paper_stage
from lightstage.capture.stage import LightSpec, Stage
from lightstage.dataset.protocols import builtin_protocol, hemisphere_grid, protocol_from_dict, resolve
from lightstage.dataset.split import SplitConfig, run_split
from lightstage.errors import LightstageError
from lightstage.ids import FrameId
from lightstage.lights import paper_number_to_index
from lightstage.pipelines.cli import main
from lightstage.records.split import load_split
from lightstage.workdir import WorkDir

PAPER_TEST = [43, 73, 105, 137, 169, 203, 233, 265, 297, 329]


def test_paper_protocol_on_paper_preset(tmp_path):
    work = WorkDir.at(tmp_path / "w")
    summary = run_split(work, SplitConfig("paper", "paper"), progress=False)
    assert summary["counts"]["train"] == 12150
    assert summary["counts"]["test"] == 180
    d = json.loads(work.split.read_text())
    assert d["counts"]["train"] == 12150 and d["counts"]["test"] == 180
    train_lights = [int(x) - 1 for x in np.linspace(1, 331, 75).astype(int)]
    test_lights = [paper_number_to_index(n) for n in PAPER_TEST]
    assert test_lights == [42, 72, 104, 136, 168, 202, 232, 264, 296, 328]
    cams = [f"cam{i:02d}" for i in range(20)]
    assert len(d["train"]["groups"]) == 9 and len(d["test"]["groups"]) == 9
    for g in d["train"]["groups"].values():
        assert g["lights"] == train_lights
        assert g["cameras"] == cams[:18]
    for g in d["test"]["groups"].values():
        assert g["lights"] == test_lights
        assert g["cameras"] == cams[18:]
    split = load_split(work.split)
    frames = list(split.test.frames())
    assert len(frames) == 180 and len(set(frames)) == 180
    assert sum(1 for _ in split.train.frames()) == 12150


def test_cli_stage_preset_prints_counts(tmp_path, capsys):
    assert main(["split", str(tmp_path / "w"), "--protocol", "paper", "--stage-preset", "paper"]) == 0
    out = capsys.readouterr().out
    assert "12150 train / 180 test" in out
    assert main(["split", str(tmp_path / "w2"), "--protocol", "nope", "--stage-preset", "paper"]) == 2


@pytest.mark.parametrize("part", ["lights", "cameras"])
def test_planted_overlap_in_protocol_fails(part):
    if part == "lights":
        d = {"lights": {"train": [0, 1, 2, 42], "test": [42, 72]}}
    else:
        d = {"cameras": {"train": ["cam00", "cam19"], "test": ["cam19"]}}
    with pytest.raises(LightstageError, match="also appear in training"):
        resolve(protocol_from_dict(d, "planted.yaml"), paper_stage())


@pytest.mark.parametrize("part", ["lights", "cameras"])
def test_planted_overlap_in_split_file_fails(tmp_path, part):
    work = WorkDir.at(tmp_path)
    run_split(work, SplitConfig("paper", "paper"), progress=False)
    d = json.loads(work.split.read_text())
    g = d["train"]["groups"]["040"]
    if part == "lights":
        g["lights"].append(328)  # paper test light 329
    else:
        g["cameras"].append("cam19")
    work.split.write_text(json.dumps(d))
    with pytest.raises(LightstageError, match="also appear in training"):
        load_split(work.split)


def test_protocol_asking_for_missing_lights_or_cameras():
    tiny = make_stage("tiny", num_cameras=4, num_lights=12, width=256, height=160)
    with pytest.raises(LightstageError, match="not on the stage"):
        resolve(protocol_from_dict({"lights": {"test": [42]}}), tiny)
    with pytest.raises(LightstageError, match="not on the stage"):
        resolve(protocol_from_dict({"cameras": {"test": ["cam19"]}}), tiny)
    with pytest.raises(LightstageError, match="the stage has 12"):
        resolve(protocol_from_dict({"lights": {"train": 12, "test": 1}}), tiny)
    with pytest.raises(LightstageError, match="unknown key"):
        protocol_from_dict({"light": {}})


def test_presets_adapt_to_small_stages():
    tiny = make_stage("tiny", num_cameras=4, num_lights=12, width=256, height=160)
    s = resolve(builtin_protocol("paper"), tiny)
    p = s.parameters
    assert p["test_cameras"] == ["cam03"] and p["train_cameras"] == ["cam00", "cam01", "cam02"]
    assert len(p["test_lights"]) == 1 and len(p["train_lights"]) == 3
    assert not set(p["test_lights"]) & set(p["train_lights"])
    small = make_stage("small", num_cameras=20, num_lights=36, width=256, height=160)
    s = resolve(builtin_protocol("paper"), small)
    assert s.counts()["train_cameras"] == 18 and s.counts()["test_cameras"] == 2
    assert s.counts()["train_lights"] == round(75 * 36 / 331)
    s = resolve(protocol_from_dict({"lights": {"train": "rest", "test": 2}}), tiny)
    assert s.counts()["train_lights"] == 10 and s.counts()["test_lights"] == 2


def test_synthetic_protocol_on_grid_stage():
    """On a stage whose lights are exactly the 7x32 hemisphere grid: 112 train lights, 10 x 10 tests."""
    grid, held = hemisphere_grid()
    assert grid.shape == (224, 3) and held.sum() == 112 and np.all(grid[:, 2] > 0)
    base = make_stage("grid", num_cameras=20, num_lights=1, width=256, height=160)
    lights = tuple(LightSpec(i, p * 1.5) for i, p in enumerate(grid))
    stage = Stage(base.name, base.cameras, lights, base.groups, base.width, base.height, base.saturation)
    s = resolve(builtin_protocol("synthetic"), stage)
    c = s.counts()
    assert c["train_lights"] == 112 and c["test_lights"] == 10 and c["test_views"] == 10 and c["test"] == 100
    assert set(s.parameters["train_lights"]) == set(np.flatnonzero(~held).tolist())
    assert set(s.parameters["test_lights"]) <= set(np.flatnonzero(held).tolist())


def test_rejected_frames_are_excluded_and_counted(tmp_path):
    work = WorkDir.at(tmp_path)
    stage = make_stage("tiny", num_cameras=4, num_lights=12, width=256, height=160)
    cap = tmp_path / "cap"
    cap.mkdir()
    stage.save(cap / "stage.yaml")
    (cap / "capture.yaml").write_text("object_name: test\n")
    work.root.mkdir(exist_ok=True)
    work.capture_pointer.write_text(str(cap))
    work.report("preprocess").parent.mkdir(parents=True)
    # cam00/000 is a training frame; cam03 light 7 a test frame; 001 is not in the split at all
    work.report("preprocess").write_text(
        json.dumps(
            {
                "rejected_frames": ["000/cam00/000", "000/cam00/001"],
                "problems": [{"frame": "040/cam03/007", "reason": "corrupt"}],
                "rejected": 2,
            }
        )
    )
    s = run_split(work, SplitConfig("paper"), progress=False)
    assert s["counts"]["train_excluded"] == 1 and s["counts"]["test_excluded"] == 1
    split = load_split(work.split)
    assert FrameId("000", "cam00", 0) not in set(split.train.frames())
    assert split.train.count() == 9 * 3 * 3 - 1 and split.test.count() == 9 * 1 * 1 - 1


def test_inline_protocol_in_stage_config(tmp_path):
    cfg = SplitConfig.from_dict(
        {"protocol": {"base": "paper", "lights": {"train": "rest"}}, "stage_preset": "paper"}
    )
    s = run_split(WorkDir.at(tmp_path), cfg, progress=False)
    assert s["counts"]["train_lights"] == 321 and s["counts"]["test_lights"] == 10
    with pytest.raises(LightstageError, match="unknown key"):
        SplitConfig.from_dict({"protocol": {"lites": {}}})
    with pytest.raises(LightstageError, match="unknown key"):
        SplitConfig.from_dict({"protocl": "paper"})
