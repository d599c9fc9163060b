"""Pipeline machinery on fake stages: config validation, records and rerun skipping, --from/--only, a corrupt
frame, a worker killed mid-run (real LocalCluster) and the whole run killed with SIGKILL (subprocess)."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

TESTS = Path(__file__).resolve().parent
if str(TESTS) not in sys.path:
    sys.path.insert(0, str(TESTS))

import test_pipeline_fakes as fakes  # noqa: E402

from lightstage.dask_executor import WORKER_MALLOC_ENV  # noqa: E402
from lightstage.errors import LightstageError  # noqa: E402
from lightstage.pipelines.cli import main as cli_main  # noqa: E402
from lightstage.pipelines.config import PipelineConfig, load_pipeline_config  # noqa: E402
from lightstage.pipelines.records import read_record  # noqa: E402
from lightstage.pipelines.runner import run_pipeline  # noqa: E402
from lightstage.workdir import WorkDir  # noqa: E402


def fake_config(**sections) -> PipelineConfig:
    data = {"entry_points": fakes.entry_points(), "cluster": {"workers": 0}, **sections}
    return PipelineConfig.from_dict(data, "test.yaml")


def outputs(work: Path) -> dict[str, bytes]:
    """Every non-report output file (visible names) with its bytes."""
    return {
        str(p.relative_to(work)): p.read_bytes()
        for p in sorted(work.rglob("*"))
        if p.is_file() and "reports" not in p.parts and not p.name.startswith(".")
    }


def finished_frames(folder: Path) -> int:
    """Fake frames written so far (not a killed writer's atomic_path temporary)."""
    return len(fakes.finished_outputs(folder))


def statuses(results) -> dict[str, str]:
    return {r.stage: r.status for r in results}


@pytest.fixture
def capture(tmp_path: Path) -> Path:
    return fakes.make_capture(tmp_path / "capture", n=12, corrupt=(3,))


# ---- config ---------------------------------------------------------------------------------------------
def test_config_errors_name_the_key(tmp_path: Path) -> None:
    cases = [
        ({"preprocs": {}}, "test.yaml: unknown key 'preprocs' (did you mean 'preprocess'?)"),
        ({"cluster": {"workers": "two"}}, "test.yaml: cluster.workers: expected an integer"),
        (
            {"cluster": {"workres": 2}},
            "test.yaml: unknown key 'cluster.workres' (did you mean 'cluster.workers'?)",
        ),
        ({"launch": {"launcher": "mpi"}}, "launch.launcher"),
        ({"preprocess": [1, 2]}, "preprocess: expected a mapping"),
        ({"entry_points": {"mesh": "x:y"}}, "entry_points.mesh"),
    ]
    for data, expected in cases:
        with pytest.raises(LightstageError, match=re.escape(expected)):
            PipelineConfig.from_dict(data, "test.yaml")
    cfg = fake_config(preprocess={"bogus": 1})
    with pytest.raises(LightstageError, match=r"test\.yaml: preprocess\.bogus: unknown key"):
        cfg.stage_config("preprocess")
    bad = tmp_path / "bad.yaml"
    bad.write_text("cluster: [unclosed\n")
    with pytest.raises(LightstageError, match="invalid YAML"):
        load_pipeline_config(bad)


def test_config_show_prints_effective_defaults(tmp_path: Path, capsys) -> None:
    path = tmp_path / "p.yaml"
    path.write_text(yaml.safe_dump({"entry_points": fakes.entry_points(), "train": {"steps": 5}}))
    assert cli_main(["config", "show", str(path)]) == 0
    shown = yaml.safe_load(capsys.readouterr().out)
    assert shown["train"] == {"steps": 5, "delay": 0.0}
    assert shown["preprocess"] == {"scale": 2, "delay": 0.0}
    assert shown["cluster"]["threads_per_worker"] == 1


def test_builtin_configs_load() -> None:
    for name in ("default", "demo"):
        cfg = load_pipeline_config(name)
        assert cfg.cluster.threads_per_worker == 1


# ---- records, skipping, --from / --only ---------------------------------------------------------------
def test_rerun_skips_and_parameter_change_reruns_downstream(tmp_path: Path, capture: Path) -> None:
    work = WorkDir.at(tmp_path / "work")
    first = run_pipeline(work, fake_config(), capture=capture, progress=False, log=lambda m: None)
    assert set(statuses(first).values()) == {"ran"}
    rec = read_record(work, "preprocess")
    assert rec["status"] == "done" and rec["errors"] == 1 and "corrupt" in rec["errors_first"][0]
    assert rec["config"] == {"scale": 2, "delay": 0.0} and rec["inputs"]["capture"]["files"] == 12
    assert (work.root / "capture.txt").read_text().strip() == str(capture.resolve())
    reference = outputs(work.root)

    again = run_pipeline(work, fake_config(), progress=False, log=lambda m: None)
    assert set(statuses(again).values()) == {"skipped"}

    # downstream of calibrate reruns; split does not read the calibration (stage table inputs) and is kept
    changed = run_pipeline(work, fake_config(calibrate={"scale": 3}), progress=False, log=lambda m: None)
    assert statuses(changed) == {
        "validate": "skipped",
        "preprocess": "skipped",
        "calibrate": "ran",
        "split": "skipped",
        "bounds": "ran",
        "shard": "ran",
        "train": "ran",
        "eval": "ran",
    }
    assert outputs(work.root)["calibration/calibration.json"] != reference["calibration/calibration.json"]

    # A changed output of an upstream stage (here: a deleted preprocess output) reruns it and downstream.
    (work.root / "preprocess" / "frames" / "005.txt").unlink()
    again = run_pipeline(work, fake_config(calibrate={"scale": 3}), progress=False, log=lambda m: None)
    assert statuses(again)["validate"] == "skipped" and statuses(again)["preprocess"] == "ran"
    assert (work.root / "preprocess" / "frames" / "005.txt").exists()

    only = run_pipeline(
        work, fake_config(calibrate={"scale": 3}), only="split", progress=False, log=lambda m: None
    )
    assert statuses(only) == {"split": "ran"}
    frm = run_pipeline(work, fake_config(calibrate={"scale": 3}), from_stage="train", progress=False)
    assert statuses(frm) == {"train": "ran", "eval": "ran"}
    with pytest.raises(LightstageError, match="--from: unknown stage"):
        run_pipeline(work, fake_config(), from_stage="mesh", progress=False)


def test_changed_train_parameter_retrains_from_scratch(tmp_path: Path, capture: Path) -> None:
    work = WorkDir.at(tmp_path / "work")
    run_pipeline(work, fake_config(train={"steps": 2}), capture=capture, progress=False, log=lambda m: None)
    res = run_pipeline(work, fake_config(train={"steps": 4}), progress=False, log=lambda m: None)
    assert statuses(res)["shard"] == "skipped" and statuses(res)["train"] == "ran"
    fresh = WorkDir.at(tmp_path / "fresh")
    run_pipeline(fresh, fake_config(train={"steps": 4}), capture=capture, progress=False, log=lambda m: None)
    assert outputs(work.root) == outputs(fresh.root)


def test_cli_run_capture_and_work(tmp_path: Path, capture: Path, monkeypatch) -> None:
    cfg = tmp_path / "p.yaml"
    cfg.write_text(yaml.safe_dump({"entry_points": fakes.entry_points()}))
    work = tmp_path / "work"
    args = ["run", str(capture), "--work", str(work), "--config", str(cfg), "--workers", "0", "--quiet"]
    assert cli_main(args) == 0
    assert read_record(WorkDir.at(work), "eval")["status"] == "done"
    assert cli_main(["run", str(capture), "--config", str(cfg)]) == 2  # no --work: one-line error


# ---- stages that could not produce every expected output ------------------------------------------------
def test_stage_with_missing_outputs_fails_is_not_done_and_is_retried(
    tmp_path: Path, capture: Path, capsys
) -> None:
    ref = WorkDir.at(tmp_path / "ref")
    run_pipeline(ref, fake_config(), capture=capture, progress=False, log=lambda m: None)

    (capture.parent / "unavailable.txt").write_text("004.txt 007.txt\n")  # storage offline for two frames
    cfg = tmp_path / "p.yaml"
    entry = {**fakes.entry_points(), "preprocess": "test_pipeline_fakes:run_preprocess_partial"}
    cfg.write_text(yaml.safe_dump({"entry_points": entry, "cluster": {"workers": 0}}))
    work = WorkDir.at(tmp_path / "work")
    args = ["run", str(capture), "--work", str(work.root), "--config", str(cfg), "--quiet"]
    assert cli_main(args) != 0  # exit codes tell the truth
    err = capsys.readouterr().err
    assert "preprocess incomplete: 2 expected output(s) missing (004.txt, 007.txt)" in err
    rec = read_record(work, "preprocess")
    assert rec["status"] == "incomplete" and rec["missing"] == ["004.txt", "007.txt"]
    assert not work.calibration.exists() and read_record(work, "calibrate") is None  # nothing downstream ran
    assert cli_main(args) != 0 and read_record(work, "preprocess")["status"] == "incomplete"  # still missing

    (
        capture.parent / "unavailable.txt"
    ).unlink()  # the cause is fixed: the rerun redoes exactly what was missing
    lines: list[str] = []
    res = run_pipeline(work, load_pipeline_config(cfg), progress=False, log=lines.append)
    assert statuses(res)["validate"] == "skipped" and statuses(res)["preprocess"] == "ran"
    assert any("preprocess: running (retrying 2 missing output(s))" in line for line in lines)
    rec = read_record(work, "preprocess")
    assert rec["status"] == "done" and rec["summary"]["counts"] == {"done": 2, "skipped": 9, "errors": 1}
    assert outputs(work.root) == outputs(ref.root)


def test_stage_that_skips_its_expected_output_is_incomplete(tmp_path: Path, capture: Path) -> None:
    entry = {**fakes.entry_points(), "calibrate": "test_pipeline_fakes:run_calibrate_nothing"}
    cfg = PipelineConfig.from_dict({"entry_points": entry, "cluster": {"workers": 0}}, "test.yaml")
    work = WorkDir.at(tmp_path / "work")
    with pytest.raises(LightstageError, match=r"calibrate incomplete: 1 expected output\(s\) missing"):
        run_pipeline(work, cfg, capture=capture, progress=False, log=lambda m: None)
    rec = read_record(work, "calibrate")
    assert rec["status"] == "incomplete" and rec["missing"] == [str(work.calibration)]
    assert read_record(work, "preprocess")["status"] == "done"


# ---- faults on a real LocalCluster -----------------------------------------------------------------------
def test_worker_killed_mid_run_completes_with_identical_outputs(
    tmp_path: Path, capture: Path, kill_process_when
) -> None:
    from lightstage.dask_executor import dask_executor

    ref = WorkDir.at(tmp_path / "ref")
    run_pipeline(ref, fake_config(), capture=capture, progress=False, log=lambda m: None)

    work = WorkDir.at(tmp_path / "work")
    frames = work.root / "preprocess" / "frames"
    with dask_executor(workers=2, dashboard="", verbose=False) as executor:
        pids = executor.worker_pids()
        with kill_process_when(pids[0], lambda: finished_frames(frames) >= 2) as killer:
            res = run_pipeline(
                work,
                fake_config(preprocess={"delay": 0.4}),
                capture=capture,
                executor=executor,
                progress=False,
                log=lambda m: None,
            )
        assert killer.killed and set(statuses(res).values()) == {"ran"}
        after = executor.worker_pids()
        # every worker, the restarted one included, got lightstage's malloc settings before it started
        malloc = executor.client.run(lambda: {k: os.environ.get(k) for k in WORKER_MALLOC_ENV})
    assert pids[0] not in after  # the worker really died (the nanny started a new one)
    assert all(env == WORKER_MALLOC_ENV for env in malloc.values()) and malloc
    assert outputs(work.root) == outputs(ref.root)


@pytest.mark.slow
def test_whole_run_killed_resumes_to_identical_outputs(tmp_path: Path) -> None:
    capture = fakes.make_capture(tmp_path / "capture", n=16, corrupt=(3,))
    ref = WorkDir.at(tmp_path / "ref")
    run_pipeline(ref, fake_config(), capture=capture, progress=False, log=lambda m: None)

    work = tmp_path / "work"
    cfg = tmp_path / "p.yaml"
    cfg.write_text(
        yaml.safe_dump(
            {
                "capture": str(capture),
                "work": str(work),
                "entry_points": fakes.entry_points(),
                "cluster": {"workers": 2, "dashboard": ""},
                "preprocess": {"delay": 0.4},
            }
        )
    )
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(TESTS), os.environ.get("PYTHONPATH", "")])}
    cmd = [sys.executable, "-m", "lightstage.pipelines.cli", "run", str(cfg), "--quiet"]
    proc = subprocess.Popen(
        cmd, env=env, start_new_session=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL
    )
    frames = work / "preprocess" / "frames"
    deadline = time.time() + 120
    while time.time() < deadline and finished_frames(frames) < 4 and proc.poll() is None:
        time.sleep(0.02)
    assert proc.poll() is None, "the run finished before it could be killed"
    os.killpg(proc.pid, signal.SIGKILL)  # the CLI and its dask workers, mid-stage
    proc.wait()
    done_before = finished_frames(frames)
    assert 4 <= done_before < 15
    assert read_record(WorkDir.at(work), "preprocess") is None

    rerun = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=300)
    assert rerun.returncode == 0, rerun.stderr
    assert "validate: up to date" in rerun.stdout
    report = read_record(WorkDir.at(work), "preprocess")
    assert report["summary"]["counts"]["skipped"] >= done_before  # finished frames were not redone
    assert outputs(work) == outputs(ref.root)
    leftovers = [
        p for p in work.rglob(".*") if p.is_file() and "reports" not in p.parts and p.name != ".lock"
    ]
    assert leftovers == []  # the rerun (holding the work lock) removed the killed writes' temporaries


@pytest.mark.slow
def test_training_step_under_torchrun(tmp_path: Path, capture: Path, monkeypatch) -> None:
    """launch.launcher: torchrun runs the train stage in torchrun's processes; the record is written as usual."""
    torchrun = Path(sys.executable).with_name("torchrun")
    if not torchrun.exists():
        pytest.skip("torchrun not installed next to this Python")
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join([str(TESTS), os.environ.get("PYTHONPATH", "")]))
    work = WorkDir.at(tmp_path / "work")
    cfg = fake_config(launch={"launcher": "torchrun", "nproc_per_node": 2, "torchrun": str(torchrun)})
    res = run_pipeline(work, cfg, capture=capture, progress=False, log=lambda m: None)
    assert statuses(res)["train"] == "ran" and statuses(res)["eval"] == "ran"
    assert read_record(work, "train")["summary"]["counts"] == {"steps": 3}
    ref = WorkDir.at(tmp_path / "ref")
    run_pipeline(ref, fake_config(), capture=capture, progress=False, log=lambda m: None)
    assert outputs(work.root) == outputs(ref.root)
