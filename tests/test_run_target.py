"""`lightstage run TARGET`: a config file, a capture directory, or a work directory that names its capture."""

from __future__ import annotations

import argparse
from pathlib import Path

from lightstage.pipelines.commands import _run_target


def _args(target: Path, config: str | None = None) -> argparse.Namespace:
    return argparse.Namespace(target=target, config=config)


def test_a_work_directory_runs_its_own_capture_and_import_config(tmp_path):
    capture = tmp_path / "capture"
    capture.mkdir()
    work = tmp_path / "work"
    work.mkdir()
    (work / "capture.txt").write_text(f"{capture}\n")
    config, cap = _run_target(_args(work))
    assert cap == str(capture) and config.work == str(work) and config.capture == str(capture)
    (work / "import.yaml").write_text("shard:\n  seed: 7\n")
    config, _ = _run_target(_args(work))
    assert config.stages["shard"] == {"seed": 7}  # the imported work dir's own pipeline config
    config, _ = _run_target(_args(work, config="default"))
    assert config.stages["shard"] == {}  # --config wins


def test_a_capture_directory_is_still_a_capture(tmp_path):
    capture = tmp_path / "capture"
    capture.mkdir()
    (capture / "stage.yaml").write_text("x: 1\n")
    _, cap = _run_target(_args(capture))
    assert cap == str(capture)
