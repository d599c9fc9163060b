"""One command per work directory (lightstage.worklock): a second command on a held WORK is refused with exit 2
naming the holder and touches nothing; a killed holder's lock is taken over and the killed run's temporaries
are removed; the real `lightstage run ... --to shard` on a tiny capture ends identical to a reference run."""

from __future__ import annotations

import hashlib
import importlib.util
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

from lightstage.pipelines.cli import LOCKING_COMMANDS, READ_ONLY_COMMANDS, build_parser
from lightstage.pipelines.cli import main as cli_main
from lightstage.workdir import WorkDir
from lightstage.worklock import hold_work_lock, read_holder, remove_leftovers

REPO = Path(__file__).resolve().parents[1]
CLI = [sys.executable, "-m", "lightstage.pipelines.cli"]
HOLDER = """
import sys, time
from lightstage.worklock import hold_work_lock
with hold_work_lock(sys.argv[1], "lightstage test-holder"):
    print("held", flush=True)
    time.sleep(120)
"""


def _tree_hash_module():
    spec = importlib.util.spec_from_file_location("tree_hash", REPO / "bench" / "tree_hash.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def listing(work: Path) -> dict[str, str]:
    """sha256 of every output file by path (bench/tree_hash.py: timings dropped, run paths replaced), view.json
    also without its `chunks` (per-run bookkeeping: how many frames a resumed run reused, tests/test_preprocess)."""
    th = _tree_hash_module()
    replacements = [(str(work.resolve()).encode(), b"<WORK>")]
    out = {}
    for p in th.output_files(work.resolve()):
        data = th.file_bytes(p, replacements)
        if p.name == "view.json":
            data = json.dumps({k: v for k, v in json.loads(data).items() if k != "chunks"}).encode()
        out[str(p.relative_to(work.resolve()))] = hashlib.sha256(data).hexdigest()
    return out


def snapshot(root: Path) -> dict[str, tuple[int, int]]:
    """Every path below root with its size and mtime: any write shows."""
    return {str(p): (p.lstat().st_size, p.lstat().st_mtime_ns) for p in sorted(root.rglob("*"))}


def group_states(pgid: int) -> list[str]:
    """The scheduler state letter of every live process in process group `pgid` (Linux /proc)."""
    states = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except (OSError, IndexError):  # exited meanwhile
            continue
        if int(fields[2]) == pgid:
            states.append(fields[0])
    return states


def stop_group(pgid: int, timeout_s: float = 30.0) -> None:
    """SIGSTOP a process group and return once every member has stopped: kill() returns before the targets
    stop (a write already in the kernel still completes), so a snapshot taken at once can see a file grow."""
    os.killpg(pgid, signal.SIGSTOP)
    deadline = time.monotonic() + timeout_s
    while any(state not in "TtZX" for state in group_states(pgid)):
        assert time.monotonic() < deadline, f"process group {pgid} did not stop: {group_states(pgid)}"
        time.sleep(0.01)


def start_holder(work: Path) -> subprocess.Popen:
    """A process holding WORK's lock (until killed); returns once it holds it."""
    proc = subprocess.Popen([sys.executable, "-c", HOLDER, str(work)], stdout=subprocess.PIPE, text=True)
    assert proc.stdout.readline().strip() == "held"
    return proc


def wait_for(condition, proc: subprocess.Popen, timeout_s: float = 300.0) -> None:
    deadline = time.time() + timeout_s
    while not condition():
        assert proc.poll() is None, "the run ended before the test could act on it"
        assert time.time() < deadline, "timed out"
        time.sleep(0.02)


def error_lines(stderr: str) -> list[str]:
    return [ln for ln in stderr.splitlines() if ln.strip()]


# ---- fast ------------------------------------------------------------------------------------------------
def test_every_command_with_a_work_directory_declares_its_lock() -> None:
    """A new subcommand taking WORK must say whether it holds the lock (else two could write one WORK)."""
    sub = next(a for a in build_parser()._actions if a.dest == "command")
    with_work = {name for name, p in sub.choices.items() if any(a.dest == "work" for a in p._actions)}
    assert with_work <= set(LOCKING_COMMANDS) | READ_ONLY_COMMANDS, with_work - set(LOCKING_COMMANDS)
    assert set(LOCKING_COMMANDS) <= set(sub.choices)
    assert {"run", "demo", "preprocess", "calibrate", "split", "bounds", "shard", "train", "eval"} <= set(
        LOCKING_COMMANDS
    )


def test_held_work_dir_is_refused_naming_the_holder_and_a_killed_holder_is_taken_over(
    tmp_path: Path, capsys
) -> None:
    work = tmp_path / "work"
    work.mkdir()
    holder = start_holder(work)
    try:
        before = snapshot(work)
        assert cli_main(["shard", str(work)]) == 2
        (line,) = error_lines(capsys.readouterr().err)
        assert line.startswith("lightstage: error: ") and f"pid {holder.pid}" in line
        assert "`lightstage test-holder`" in line and "since " in line
        # the work directory named by a pipeline config's `work:` is locked too
        cfg = tmp_path / "p.yaml"
        cfg.write_text(yaml.safe_dump({"capture": str(tmp_path / "capture"), "work": str(work)}))
        assert cli_main(["run", str(cfg)]) == 2
        assert f"pid {holder.pid}" in capsys.readouterr().err
        assert snapshot(work) == before  # the refused commands wrote nothing
    finally:
        holder.kill()
        holder.wait()
    assert read_holder(work).pid == holder.pid  # the dead holder's record is still there...
    with hold_work_lock(work, "lightstage next") as lock:  # ...but its lock died with it
        assert read_holder(work).pid == os.getpid() == lock.holder.pid
    assert read_holder(work) is None  # an idle work directory's lock file is empty


def test_leftovers_of_killed_writers_are_removed_and_nothing_else(tmp_path: Path) -> None:
    work = WorkDir.at(tmp_path / "work")
    capture = work.root / "capture"  # a raw capture kept inside WORK (the demo does)
    leftovers = [
        work.train_dir / ".loss.k1ll3d0a.tmp.png",
        work.train_dir / ".checkpoint.a0b1c2d3.tmp.pt",
        work.root / ".manifest.zz_9yy8x.tmp.json",
        work.preprocess_dir / "frames" / "000" / "cam00" / ".007.abcdefgh.tmp.exr",
        work.shards_dir / "test" / ".index.qwertyui.tmp",
    ]
    kept = [
        work.root / ".lock",
        work.root / ".demo-capture.json",
        work.report("train").parent / ".train-launch.json",
        work.train_dir / "loss.png",
        work.preprocess_dir / "frames" / "000" / "cam00" / "007.exr",
        capture / "frames" / ".001.abcdefgh.tmp.exr",  # never touch the raw capture
    ]
    for p in leftovers + kept:
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_bytes(b"x")
    work.capture_pointer.write_text(f"{capture}\n")
    finished, unfinished = tmp_path / "finished", tmp_path / "unfinished"
    (work.shards_dir / "tmp").mkdir()
    (work.shards_dir / "tmp" / "view_00000.npy").write_bytes(b"x")
    (work.shards_dir / "manifest.json").write_text("{}")
    with hold_work_lock(work.root, "lightstage test") as lock:
        assert sorted(lock.removed) == sorted([*leftovers, work.shards_dir / "tmp"])
    assert not any(p.exists() for p in leftovers) and all(p.exists() for p in kept)
    assert not (work.shards_dir / "tmp").exists()  # the shard finished: its scratch folder is garbage
    # without the manifest, shards/tmp is an interrupted shard's resume state: kept
    for root, manifest in ((finished, True), (unfinished, False)):
        w = WorkDir.at(root)
        (w.shards_dir / "tmp").mkdir(parents=True)
        if manifest:
            (w.shards_dir / "manifest.json").write_text("{}")
        remove_leftovers(w)
        assert (w.shards_dir / "tmp").exists() != manifest


# ---- the real pipeline on a tiny capture -------------------------------------------------------------------
@pytest.fixture(scope="module")
def pipeline_config(tmp_path_factory) -> Path:
    """In-process stages, one pycolmap thread (SfM is deterministic only then)."""
    path = tmp_path_factory.mktemp("cfg") / "pipeline.yaml"
    path.write_text(yaml.safe_dump({"cluster": {"workers": 0}, "calibrate": {"num_threads": 1}}))
    return path


@pytest.fixture(scope="module")
def reference(tiny_capture: Path, pipeline_config: Path, tmp_path_factory) -> dict[str, str]:
    work = tmp_path_factory.mktemp("ref") / "work"
    args = ["run", str(tiny_capture), "--work", str(work), "--config", str(pipeline_config)]
    assert cli_main([*args, "--to", "shard", "--quiet"]) == 0
    return listing(work)


def run_command(capture: Path, work: Path, config: Path) -> list[str]:
    return [*CLI, "run", str(capture), "--work", str(work), "--config", str(config), "--to", "shard"]


@pytest.mark.slow
def test_second_run_is_refused_and_the_first_ends_identical_to_a_reference(
    tiny_capture: Path, pipeline_config: Path, reference: dict[str, str], tmp_path: Path
) -> None:
    work = tmp_path / "work"
    cmd = [*run_command(tiny_capture, work, pipeline_config), "--quiet"]
    first = subprocess.Popen(
        cmd, start_new_session=True, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True
    )
    try:
        holds = lambda: (h := read_holder(work)) is not None and h.pid == first.pid  # noqa: E731
        wait_for(lambda: holds() and (work / "preprocess").is_dir(), first)  # mid-preprocess
        # Hold the first still while the second tries: its whole process group (the stages' pool workers
        # write too), and only once all of it has stopped (once a temporary grew between the snapshots).
        stop_group(first.pid)
        try:
            before = snapshot(work)
            second = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
            assert snapshot(work) == before  # the second wrote nothing (no temp, no cleanup)
        finally:
            os.killpg(first.pid, signal.SIGCONT)
        assert second.returncode == 2
        (line,) = error_lines(second.stderr)
        assert line.startswith(f"lightstage: error: {work}: work directory in use")
        assert f"pid {first.pid}" in line and "`lightstage run " in line and "since " in line
        assert first.wait(timeout=600) == 0, first.stderr.read()
    finally:
        if first.poll() is None:
            first.kill()
            first.wait()
    assert listing(work) == reference


@pytest.mark.slow
def test_killed_run_is_taken_over_and_its_leftovers_removed(
    tiny_capture: Path, pipeline_config: Path, reference: dict[str, str], tmp_path: Path
) -> None:
    work = WorkDir.at(tmp_path / "work")
    cmd = [*run_command(tiny_capture, work.root, pipeline_config), "--quiet"]
    run = subprocess.Popen(cmd, start_new_session=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    frames = work.preprocess_dir / "frames"
    wait_for(lambda: frames.is_dir() and any(frames.rglob("*.exr")), run)
    os.killpg(run.pid, signal.SIGKILL)  # the CLI and anything it started, mid-preprocess
    run.wait()
    assert read_holder(work.root).pid == run.pid  # the dead run's record; its flock is gone
    planted = [work.train_dir / ".loss.k1ll3d0a.tmp.png", work.preprocess_dir / ".stats.abcdefgh.tmp.json"]
    for p in planted:  # what a kill mid-write leaves (lightstage.atomic's temporaries)
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_bytes(b"partial")
    rerun = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert rerun.returncode == 0, rerun.stderr
    assert "lightstage: note: removed" in rerun.stderr
    assert not any(p.exists() for p in planted)
    assert read_holder(work.root) is None  # released at exit
    assert listing(work.root) == reference
