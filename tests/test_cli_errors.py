"""Operator mistakes and environment faults end in one `lightstage: error:` line and a non-zero exit, never a
traceback (issue 21 item 5): `--work` naming a file, a full disk during training's previews and checkpoints,
`optim.lr: -1`, and resuming a training with another config (refused naming each differing key; more steps and
other documented-safe keys are accepted)."""

from __future__ import annotations

import errno
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import torch
import yaml
from support.fixtures import make_synthetic_work
from support.training import micro_config

from lightstage.dataset.shard_config import ShardConfig
from lightstage.dataset.shards import run_shard
from lightstage.dataset.split import SplitConfig, run_split
from lightstage.pipelines.cli import main as cli_main
from lightstage.training.checkpoint import CHECKPOINT_NAME, load_checkpoint
from lightstage.training.config import merge
from lightstage.workdir import WorkDir


def one_error_line(stderr: str) -> str:
    """The single `lightstage: error:` line a failed command must print (and nothing like a traceback)."""
    lines = [ln for ln in stderr.splitlines() if ln.strip()]
    assert "Traceback" not in stderr, stderr
    errors = [ln for ln in lines if ln.startswith("lightstage: error: ")]
    assert len(errors) == 1, stderr
    return errors[0]


@pytest.fixture(scope="module")
def sharded(tmp_path_factory) -> WorkDir:
    """A synthetic work directory with split and shards (no simulator, preprocess or calibration needed)."""
    work, _ = make_synthetic_work(tmp_path_factory.mktemp("sharded"))
    run_split(work, SplitConfig("paper"), progress=False)
    run_shard(work, ShardConfig(rays_per_image=64, rays_per_shard=256, workers=1), progress=False)
    return work


@pytest.fixture
def work(sharded: WorkDir, tmp_path: Path) -> WorkDir:
    """A private copy of `sharded` to train in."""
    root = tmp_path / "work"
    shutil.copytree(sharded.root, root)
    return WorkDir.at(root)


def write_config(path: Path, steps: int = 2, **changes) -> Path:
    """The micro training config (as tests/test_trainer.py uses) with one preview per step, plus `changes`."""
    cfg = micro_config(steps=steps).to_dict()
    cfg["eval"].update(every=1, images=1)
    path.write_text(yaml.safe_dump(merge(cfg, changes)))
    return path


def train(work: WorkDir, config: Path, *extra: str) -> int:
    return cli_main(["train", str(work.root), "--config", str(config), "--device", "cpu", "--quiet", *extra])


# ---- the work directory ----------------------------------------------------------------------------------
def test_work_pointing_at_a_file_is_one_line(tmp_path: Path, capsys) -> None:
    capture = tmp_path / "capture"
    capture.mkdir()
    afile = tmp_path / "afile"
    afile.write_text("not a folder")
    for args in (
        ["run", str(capture), "--work", str(afile)],
        ["preprocess", str(capture), "--work", str(afile)],
        ["calibrate", str(afile)],
        ["split", str(afile)],
        ["shard", str(afile)],
        ["train", str(afile)],
        ["eval", str(afile)],
    ):
        assert cli_main(args) == 2, args
        line = one_error_line(capsys.readouterr().err)
        assert line == f"lightstage: error: {afile}: not a directory (the work directory must be a folder)"
    assert afile.read_text() == "not a folder"
    assert cli_main(["train", str(tmp_path / "nowhere")]) == 2
    assert f"{tmp_path / 'nowhere'}: work directory not found (make one with" in one_error_line(
        capsys.readouterr().err
    )
    assert not (tmp_path / "nowhere").exists()  # a stage that needs WORK does not create it


def test_negative_learning_rate_is_one_line(work: WorkDir, tmp_path: Path, capsys) -> None:
    config = write_config(tmp_path / "bad.yaml", optim={"lr": -1})
    assert train(work, config) == 2
    assert "optim.lr: must be > 0, got -1" in one_error_line(capsys.readouterr().err)


# ---- a full disk during training ----------------------------------------------------------------------------
class _SilentlyFailingOutput:
    """OpenImageIO's ImageOutput on a full disk: the file is created, nothing lands in it, every call succeeds."""

    def open(self, name: str, spec) -> bool:
        Path(name).write_bytes(b"")
        return True

    def write_image(self, pixels) -> bool:
        return True

    def close(self) -> bool:
        return True

    def geterror(self) -> str:
        return ""


def test_disk_full_during_previews_is_one_line(work: WorkDir, tmp_path: Path, monkeypatch, capsys) -> None:
    import OpenImageIO as oiio

    class FullDisk:
        f_bavail, f_frsize = 0, 4096

    monkeypatch.setattr(oiio.ImageOutput, "create", staticmethod(lambda name: _SilentlyFailingOutput()))
    monkeypatch.setattr("lightstage.frames.os.statvfs", lambda path: FullDisk())
    assert train(work, write_config(tmp_path / "micro.yaml")) == 1
    preview = work.train_dir / "previews" / "step0000001_0.png"
    line = one_error_line(capsys.readouterr().err)
    assert line == f"lightstage: error: {preview}: No space left on device (image write cut at 0 bytes)"
    assert not (work.train_dir / "previews").exists() or not list((work.train_dir / "previews").iterdir())


def test_disk_full_while_checkpointing_is_one_line(
    work: WorkDir, tmp_path: Path, monkeypatch, capsys
) -> None:
    write_bytes = Path.write_bytes

    def full(self: Path, data) -> int:  # a buffered write to a full disk: ENOSPC naming no file
        if self.name.startswith(".checkpoint."):
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return write_bytes(self, data)

    monkeypatch.setattr(Path, "write_bytes", full)
    assert train(work, write_config(tmp_path / "micro.yaml")) == 1
    line = one_error_line(capsys.readouterr().err)
    assert line == f"lightstage: error: {work.train_dir / CHECKPOINT_NAME}: No space left on device"
    assert not list(work.train_dir.glob(".checkpoint.*"))  # the temporary is gone


def _can_mount_tmpfs() -> bool:
    if shutil.which("unshare") is None:
        return False
    probe = "mkdir -p /tmp/.lightstage-probe && mount -t tmpfs -o size=4k tmpfs /tmp/.lightstage-probe"
    return subprocess.run(["unshare", "--mount", "sh", "-c", probe], capture_output=True).returncode == 0


@pytest.mark.skipif(not _can_mount_tmpfs(), reason="needs a private mount namespace (unshare --mount, root)")
def test_real_full_disk_during_previews_is_one_line(work: WorkDir, tmp_path: Path) -> None:
    """The same on a real full file system: a 4 KiB tmpfs over train/previews in a private mount namespace."""
    previews = work.train_dir / "previews"
    previews.mkdir(parents=True)
    script = (
        'mount -t tmpfs -o size=4k tmpfs "$1" && head -c 3072 /dev/zero > "$1/filler" && shift && exec "$@"'
    )
    config = write_config(tmp_path / "micro.yaml")
    cmd = [sys.executable, "-m", "lightstage.pipelines.cli", "train", str(work.root), "--config", str(config)]
    cmd += ["--device", "cpu", "--quiet"]
    proc = subprocess.run(
        ["unshare", "--mount", "sh", "-c", script, "sh", str(previews), *cmd], capture_output=True, text=True
    )
    assert proc.returncode == 1, proc.stderr
    line = one_error_line(proc.stderr)
    assert line.startswith(f"lightstage: error: {previews / 'step0000001_0.png'}: No space left on device")


# ---- resuming with another config -------------------------------------------------------------------------
def test_resume_with_other_layer_sizes_is_refused_naming_the_key(
    work: WorkDir, tmp_path: Path, capsys
) -> None:
    assert train(work, write_config(tmp_path / "a.yaml")) == 0
    saved = (work.train_dir / CHECKPOINT_NAME).read_bytes()
    capsys.readouterr()
    wider = write_config(tmp_path / "b.yaml", model={"mlp": {"width": 32}})
    assert train(work, wider) == 2
    line = one_error_line(capsys.readouterr().err)
    assert "cannot resume with a config different from the checkpoint's (model.mlp.width: 16 → 32)" in line
    assert (work.train_dir / CHECKPOINT_NAME).read_bytes() == saved  # nothing was overwritten


def test_resume_with_another_schedule_is_refused_naming_every_key(
    work: WorkDir, tmp_path: Path, capsys
) -> None:
    """Same shapes, so the tensors would load: before, the old lr was silently kept (Adam's param groups and
    the scheduler's base lr come from the checkpoint) while the checkpoint recorded the new config."""
    base = micro_config(steps=2).optim
    assert train(work, write_config(tmp_path / "a.yaml")) == 0
    capsys.readouterr()
    other = write_config(tmp_path / "b.yaml", optim={"lr": base.lr * 2, "warmup_steps": 5}, seed=7)
    assert train(work, other, "--steps", "4") == 2
    line = one_error_line(capsys.readouterr().err)
    assert f"optim.lr: {base.lr} → {base.lr * 2}" in line
    assert f"optim.warmup_steps: {base.warmup_steps} → 5" in line and "seed: 0 → 7" in line
    assert "optim.steps:" not in line  # more steps is fine
    assert load_checkpoint(work.train_dir / CHECKPOINT_NAME)["step"] == 2


def test_resume_with_more_steps_and_other_frequencies_is_accepted(
    work: WorkDir, tmp_path: Path, capsys
) -> None:
    assert train(work, write_config(tmp_path / "a.yaml")) == 0
    more = write_config(tmp_path / "b.yaml", steps=4, log_every=2, checkpoint_every=3, eval={"every": 2})
    assert train(work, more) == 0
    ck = load_checkpoint(work.train_dir / CHECKPOINT_NAME)
    assert ck["step"] == 4 and ck["config"]["optim"]["steps"] == 4  # the checkpoint records what ran
    capsys.readouterr()
    assert train(work, more, "--steps", "3") == 2  # fewer steps than the checkpoint's config
    assert "(optim.steps: 4 → 3)" in one_error_line(capsys.readouterr().err)


def test_checkpoint_that_does_not_fit_the_model_is_one_line(work: WorkDir, tmp_path: Path, capsys) -> None:
    """A checkpoint without its config (older or foreign) whose tensors do not fit: one line, not torch's dump."""
    assert train(work, write_config(tmp_path / "a.yaml")) == 0
    path = work.train_dir / CHECKPOINT_NAME
    ck = torch.load(path, weights_only=True)
    del ck["config"]
    torch.save(ck, path)
    capsys.readouterr()
    assert train(work, write_config(tmp_path / "b.yaml", model={"mlp": {"width": 32}})) == 2
    line = one_error_line(capsys.readouterr().err)
    assert line.startswith(f"lightstage: error: {path}: does not fit this model (")


# ---- damaged shards ---------------------------------------------------------------------------------------
def _shard_records(work: WorkDir) -> list[dict]:
    from lightstage.records.shards import load_manifest

    return load_manifest(work.shards_dir)["shards"]


def test_truncated_shard_stops_training_naming_it(work: WorkDir, tmp_path: Path, capsys) -> None:
    """A shard cut to 1000 bytes (a copy cut short) is refused before training reads anything, naming the shard
    and the command that rebuilds it, even when the short run would never reach that shard."""
    last = work.shards_dir / _shard_records(work)[-1]["file"]
    last.write_bytes(last.read_bytes()[:1000])
    config = write_config(tmp_path / "micro.yaml", eval={"every": 0})
    assert train(work, config) == 2
    line = one_error_line(capsys.readouterr().err)
    assert f"{last}: is 1000 bytes, manifest says" in line
    assert f"lightstage shard {work.root.resolve()} --force" in line
    assert not (work.train_dir / CHECKPOINT_NAME).exists()
    # the command the message names rebuilds the shards (the fixture's settings as flags); then training runs
    flags = ["--workers", "1", "--rays-per-image", "64", "--rays-per-shard", "256"]
    assert cli_main(["shard", str(work.root), "--force", *flags]) == 0
    assert train(work, config) == 0


def test_foreign_shard_and_truncated_test_image_are_refused(work: WorkDir, tmp_path: Path, capsys) -> None:
    """A shard of the right size from another run (its checksum differs) and a truncated test image: each an
    error naming the file, never read."""
    paths = [work.shards_dir / r["file"] for r in _shard_records(work)]
    originals = [p.read_bytes() for p in paths]
    for p, mine, other in zip(paths, originals, originals[1:] + originals[:1], strict=True):
        p.write_bytes(other[: len(mine)].ljust(len(mine), b"\0"))  # each holds another's rays, its own size
    config = write_config(tmp_path / "micro.yaml", eval={"every": 0})
    assert train(work, config) == 2
    assert "checksum mismatch" in one_error_line(capsys.readouterr().err)
    for p, data in zip(paths, originals, strict=True):
        p.write_bytes(data)
    from lightstage.records.shards import read_test_index

    test = work.shards_dir / read_test_index(work.shards_dir)[0]["file"]
    test.write_bytes(test.read_bytes()[:1000])
    assert train(work, write_config(tmp_path / "previews.yaml")) == 2  # previews read the test images
    assert f"{test}: is 1000 bytes, manifest says" in one_error_line(capsys.readouterr().err)
