"""The demo's model (the `cpu` config) on a simulated capture, through the real stages: it must beat the
constant-colour baseline on the masked metric by a wide margin and stay below the ceiling."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

from lightstage.dataset.shard_config import ShardConfig
from lightstage.dataset.shards import run_shard
from lightstage.dataset.split import SplitConfig, run_split
from lightstage.training.config import load_config
from lightstage.training.evaluate import run_eval
from lightstage.training.train_stage import run_train
from lightstage.workdir import WorkDir


def train_and_eval(capture: Path, root: Path) -> dict:
    """The real stages: preprocess, true calibration, split (every non-test light trains), shard, 300 steps of
    the `cpu` config, eval; returns the eval means."""
    from lightstage.preprocess.config import PreprocessConfig
    from lightstage.preprocess.run import run_preprocess

    work = WorkDir.at(root)
    work.root.mkdir()
    work.capture_pointer.write_text(str(capture))
    run_preprocess(work, PreprocessConfig(), progress=False)
    work.calibration.parent.mkdir(parents=True, exist_ok=True)
    shutil.copy(capture / "ground_truth" / "geometry.json", work.calibration)
    split = SplitConfig.from_dict({"protocol": {"base": "paper", "lights": {"train": "rest"}}})
    run_split(work, split, progress=False)
    run_shard(work, ShardConfig(workers=1), progress=False)
    cfg = load_config("cpu", {"optim": {"steps": 300, "batch_rays": 512}, "eval": {"every": 0}})
    run_train(work, cfg, progress=False, device="cpu")
    return run_eval(work, progress=False, device="cpu")["mean"]


@pytest.mark.slow
def test_cpu_model_beats_the_baseline_on_the_masked_metric(tiny_capture, tmp_path):
    mean = train_and_eval(tiny_capture, tmp_path / "work")
    assert mean["psnr"] >= mean["baseline_psnr"] + 8.0, mean
    assert mean["psnr"] < mean["ceiling_psnr"], mean
