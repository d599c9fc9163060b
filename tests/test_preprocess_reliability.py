"""Preprocess reliability (issues 21 and 24): the two decoders give identical outputs; environment faults
(permission denied, disk full) fail the stage without being remembered, so a rerun after the fix equals a clean
run; failed views and a path_template matching nothing exit non-zero; a FIFO in place of a frame and a stalled
read are reported (never a hang); validate and preprocess reject negative pixels alike; stale temp files of a
live process are kept."""

from __future__ import annotations

import errno
import json
import os
import subprocess
import sys
import threading
from pathlib import Path

import pytest
from test_preprocess import _snapshot, _subset_capture, _work

import lightstage.exr_header as exr_header
import lightstage.frames as frames
import lightstage.records.processed as processed
from lightstage.errors import EnvironmentFault, LightstageError, StageIncomplete
from lightstage.exr_header import prefetch_file, read_exr_header
from lightstage.frames import write_exr
from lightstage.preprocess.config import PreprocessConfig
from lightstage.preprocess.run import run_preprocess

pytestmark = pytest.mark.timeout(300)


@pytest.fixture(scope="module")
def small_capture(tiny_capture: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """One group x two cameras of tiny (24 frames), copied: tests damage their own copies of it."""
    return _subset_capture(tiny_capture, tmp_path_factory.mktemp("cap") / "cap", groups=1, cameras=2)


@pytest.fixture(scope="module")
def clean(small_capture: Path, tmp_path_factory: pytest.TempPathFactory) -> dict[str, bytes]:
    """The outputs of an uninterrupted run with the default config."""
    work = _work(tmp_path_factory.mktemp("clean"), small_capture)
    run_preprocess(work, PreprocessConfig(chunk_lights=5), progress=False)
    return _snapshot(work)


def _copy(capture: Path, dst: Path) -> Path:
    import shutil

    shutil.copytree(capture, dst, symlinks=False)
    return dst


# ---- issue 24: the decode paths ---------------------------------------------------------------------------------
@pytest.mark.parametrize("sfm_max_side", [2048, 128])  # SfM image at raw / 1 (tiny's default) and at raw / 2
def test_both_decoders_give_identical_frames_statistics_and_sfm_images(
    small_capture: Path, tmp_path: Path, sfm_max_side: int, monkeypatch: pytest.MonkeyPatch
) -> None:
    """openexr, bands and auto (which times each in a run of a fresh process's first frames) give byte-identical
    outputs; every decoder saves the SfM frames while it has the raw frame decoded (no second decode)."""
    from lightstage.preprocess import decoder_choice, sfm_image

    monkeypatch.setattr(decoder_choice, "_PROCESS_CHOOSER", decoder_choice.DecoderChooser())  # a new process
    second_decodes = []
    monkeypatch.setattr(sfm_image, "_decode_at_factor", lambda src, lt: second_decodes.append(lt))
    outs, reports = {}, {}
    for decoder in ("openexr", "bands", "auto"):
        work = _work(tmp_path / decoder, small_capture)
        cfg = PreprocessConfig(chunk_lights=5, decoder=decoder, sfm_max_side=sfm_max_side)
        run_preprocess(work, cfg, progress=False)
        reports[decoder] = json.loads(work.report("preprocess").read_text())
        outs[decoder] = _snapshot(work)
    assert second_decodes == []
    for decoder in ("openexr", "bands"):
        assert reports[decoder]["decoder"] == decoder
        assert reports[decoder]["decoders"]["frames"] == {decoder: 24}
    auto = reports["auto"]["decoders"]
    assert auto["configured"] == "auto" and sum(auto["frames"].values()) == 24
    # the in-process executor is one process: it probed both decoders, then kept the cheaper
    probes = decoder_choice.PROBE_FRAMES + 1
    assert min(auto["frames"].values()) >= probes and len(auto["frames"]) == 2
    assert set(auto["probe_cpu_s"][-1]) == {"openexr", "bands"}
    assert reports["auto"]["decoder"] == decoder_choice.process_chooser().chosen
    a = outs["openexr"]
    assert any("/frames/" in k for k in a) and any(k.endswith("stats.npz") for k in a)
    for b in (outs["bands"], outs["auto"]):
        assert sorted(a) == sorted(b)
        assert [k for k in a if a[k] != b[k]] == []


def test_the_downscale_kernels_give_the_outputs_of_the_opencv_path(
    small_capture: Path, clean: dict[str, bytes], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Frames, saturation masks, statistics and view outputs are byte-identical with the numba kernels
    (`clean`) and without them (PyTorch + cv2.resize + numpy, the code before the kernels)."""
    from lightstage.preprocess import area_kernel

    assert area_kernel.available()
    monkeypatch.setattr(area_kernel._SWITCH, "_enabled", False)
    work = _work(tmp_path / "work", small_capture)
    run_preprocess(work, PreprocessConfig(chunk_lights=5), progress=False)
    b = _snapshot(work)
    assert sorted(clean) == sorted(b)
    assert [k for k in clean if clean[k] != b[k]] == []


# ---- environment faults are not remembered ---------------------------------------------------------------------
def test_permission_error_fixed_between_runs_gives_the_clean_outputs(
    small_capture: Path, clean: dict[str, bytes], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    denied = str(small_capture / "frames" / "000" / "cam01" / "007.exr")
    real = exr_header._read_all

    def read_all(path: Path) -> None:
        if str(path) == denied:
            raise PermissionError(errno.EACCES, "Permission denied", str(path))
        real(path)

    work = _work(tmp_path / "work", small_capture)
    monkeypatch.setattr(exr_header, "_read_all", read_all)
    with pytest.raises(StageIncomplete) as e:
        run_preprocess(work, PreprocessConfig(chunk_lights=5), progress=False)
    assert "000/cam01" in e.value.missing and "1 of 2 views failed" in str(e.value)
    report = json.loads(work.report("preprocess").read_text())
    assert report["status"] == "incomplete" and report["missing"]["views"] == ["000/cam01"]
    assert report["problems"] == []  # not remembered as a bad frame
    assert "Permission denied" in report["errors"][0] and denied in report["errors"][0]
    monkeypatch.setattr(exr_header, "_read_all", real)  # the cause is fixed
    summary = run_preprocess(work, PreprocessConfig(chunk_lights=5), progress=False)
    assert summary["status"] == "complete" and summary["problems"] == 0
    got = _snapshot(work)
    assert sorted(got) == sorted(clean) and [k for k in got if got[k] != clean[k]] == []


def test_disk_full_moment_gives_the_clean_outputs(
    small_capture: Path, clean: dict[str, bytes], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    real = processed.write_exr_parts
    full = {"on": True, "hits": 0}

    def write(path, parts, **kw):  # noqa: ANN001, ANN003, ANN202
        if full["on"] and Path(path).name == "009.exr":  # the disk is full whenever this frame is written
            full["hits"] += 1
            raise OSError(errno.ENOSPC, "No space left on device", str(path))
        return real(path, parts, **kw)

    work = _work(tmp_path / "work", small_capture)
    monkeypatch.setattr(processed, "write_exr_parts", write)
    with pytest.raises(StageIncomplete):
        run_preprocess(work, PreprocessConfig(chunk_lights=5), progress=False)
    assert full["hits"] > 2  # the task was retried (twice per view) before the stage gave up
    report = json.loads(work.report("preprocess").read_text())
    assert report["problems"] == [] and "No space left" in report["errors"][0]
    assert sorted(report["missing"]["views"]) == ["000/cam00", "000/cam01"]
    full["on"] = False  # the disk has room again
    summary = run_preprocess(work, PreprocessConfig(chunk_lights=5), progress=False)
    assert summary["status"] == "complete"
    got = _snapshot(work)
    assert sorted(got) == sorted(clean) and [k for k in got if got[k] != clean[k]] == []


# ---- exit codes that tell the truth -------------------------------------------------------------------------------
def _cli(*args: str) -> subprocess.CompletedProcess:
    cmd = [sys.executable, "-m", "lightstage.pipelines.cli", "preprocess", *args, "--quiet"]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=240)


def test_failed_views_exit_non_zero_and_the_report_names_them(small_capture: Path, tmp_path: Path) -> None:
    work = tmp_path / "work"
    blocked = work / "preprocess" / "frames" / "000" / "cam01" / "003.exr"
    blocked.mkdir(parents=True)  # a directory where a processed frame must go: that view cannot be written
    done = _cli(str(small_capture), "--work", str(work))
    assert done.returncode != 0
    last = done.stderr.strip().splitlines()[-1]
    assert last.startswith("lightstage: error: preprocess: 1 of 2 views failed") and str(blocked) in last
    report = json.loads((work / "reports" / "preprocess.json").read_text())
    assert report["status"] == "incomplete" and report["missing"]["views"] == ["000/cam01"]
    assert report["problems"] == []  # a fault of the work directory is not a bad frame


def test_more_bad_frames_than_the_limit_exit_non_zero(small_capture: Path, tmp_path: Path) -> None:
    cap = _copy(small_capture, tmp_path / "cap")
    for light in range(3):  # 3 of 24 frames garbage: 12.5% > max_bad_fraction 0.05
        (cap / "frames" / "000" / "cam00" / f"{light:03d}.exr").write_bytes(b"not an exr")
    work = tmp_path / "work"
    done = _cli(str(cap), "--work", str(work))
    assert done.returncode != 0
    assert done.stderr.strip().splitlines()[-1].startswith("lightstage: error: preprocess: 3 of 24 frames")
    report = json.loads((work / "reports" / "preprocess.json").read_text())
    assert report["status"] == "incomplete" and len(report["missing"]["frames"]) == 3
    assert "more than max_bad_fraction" in report["failure"] and report["missing"]["views"] == []


def test_path_template_matching_no_file_fails_naming_it(small_capture: Path, tmp_path: Path) -> None:
    cap = _copy(small_capture, tmp_path / "cap")
    text = (cap / "capture.yaml").read_text()
    (cap / "capture.yaml").write_text(text + "path_template: raw/{group}_{camera}_{light:03d}.exr\n")
    done = _cli(str(cap), "--work", str(tmp_path / "work"))
    assert done.returncode != 0
    last = done.stderr.strip().splitlines()[-1]
    assert last.startswith("lightstage: error:") and "raw/{group}_{camera}_{light:03d}.exr" in last
    assert "matches no frame" in last


# ---- file types and stalled reads -------------------------------------------------------------------------------------
def test_fifo_frame_is_a_bad_frame_named_at_once(small_capture: Path, tmp_path: Path) -> None:
    cap = _copy(small_capture, tmp_path / "cap")
    fifo = cap / "frames" / "000" / "cam00" / "004.exr"
    fifo.unlink()
    os.mkfifo(fifo)
    with pytest.raises(LightstageError, match="FIFO"):
        read_exr_header(fifo)  # no open before the check: this returns instead of waiting for a writer
    work = _work(tmp_path / "work", cap)
    run_preprocess(work, PreprocessConfig(read_timeout_s=30.0, max_bad_fraction=0.1), progress=False)
    report = json.loads(work.report("preprocess").read_text())
    assert [p["frame"] for p in report["problems"]] == ["000/cam00/004"]
    assert str(fifo) in report["problems"][0]["reason"] and "FIFO" in report["problems"][0]["reason"]


def test_stalled_read_fails_within_the_timeout_naming_the_frame(
    small_capture: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    release = threading.Event()
    monkeypatch.setattr(exr_header, "_read_all", lambda path: release.wait(60))  # storage that never answers
    frame = small_capture / "frames" / "000" / "cam00" / "001.exr"
    try:
        with pytest.raises(EnvironmentFault, match="read stalled") as e:
            prefetch_file(frame, 0.3)
        assert str(frame) in str(e.value)
    finally:
        release.set()


# ---- one pixel policy ---------------------------------------------------------------------------------------------------
def test_negative_pixels_are_rejected_by_validate_and_preprocess_alike(
    small_capture: Path, tmp_path: Path
) -> None:
    from lightstage.capture.frame_checks import decode_check

    cap = _copy(small_capture, tmp_path / "cap")
    path = cap / "frames" / "000" / "cam01" / "003.exr"
    pixels = frames.read_exr(path)
    pixels[10, 20, 1] = -0.25
    pixels[11, 20, 0] = -0.0  # negative zero is zero, not negative
    write_exr(path, pixels)
    checked = decode_check({"path": str(path), "saturation": 4.4019})
    assert checked["status"] == "negative" and "1 negative samples" in checked["message"]
    work = _work(tmp_path / "work", cap)
    run_preprocess(work, PreprocessConfig(max_bad_fraction=0.1), progress=False)
    report = json.loads(work.report("preprocess").read_text())
    assert [p["frame"] for p in report["problems"]] == ["000/cam01/003"]
    assert "negative pixels (1 negative samples)" in report["problems"][0]["reason"]
    assert frames.pixel_verdict(0, 1).status == checked["status"]  # the one shared policy


# ---- stale temp files ------------------------------------------------------------------------------------------------------
def test_stale_temps_of_a_live_process_are_kept(tmp_path: Path) -> None:
    from lightstage.preprocess.jobs import remove_stale_temps

    live = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    try:
        names = {
            "live": f".005.{live.pid}.abcd1234.tmp.exr",
            "dead": f".005.{dead.pid}.abcd1234.tmp.exr",
            "mine": f".005.{os.getpid()}.abcd1234.tmp.exr",
            "legacy": ".005.abcd1234.tmp.exr",
            "other": f".006.{dead.pid}.abcd1234.tmp.exr",
        }
        for name in names.values():
            (tmp_path / name).write_bytes(b"x")
        remove_stale_temps(tmp_path, ["005"])
        left = {k for k, n in names.items() if (tmp_path / n).exists()}
        assert left == {"live", "other"}
    finally:
        live.kill()
        live.wait()
