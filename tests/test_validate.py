"""Capture validation: a small hand-built capture with planted problems, the CLI, decoder isolation, the
pipeline stage entry point, and check_pixels."""

from __future__ import annotations

import json
import os
import signal
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from lightstage.capture.decoder_pool import DecoderPool
from lightstage.capture.frame_checks import STATUSES, decode_check
from lightstage.capture.layout import CaptureInfo, open_capture, save_capture_info
from lightstage.capture.presets import make_stage
from lightstage.capture.validate import ValidateConfig, run_validate, validate_capture
from lightstage.errors import LightstageError
from lightstage.frames import check_pixels, write_exr
from lightstage.pipelines.cli import main
from lightstage.workdir import WorkDir

W, H = 16, 12


def make_capture(root: Path, seed: int = 0) -> Path:
    """2 groups x 2 cameras x 3 lights of 16x12 half RGB frames, all valid."""
    stage = make_stage("tiny", num_cameras=2, num_lights=3, width=W, height=H, num_groups=2)
    root.mkdir(parents=True, exist_ok=True)
    stage.save(root / "stage.yaml")
    save_capture_info(CaptureInfo(), root / "capture.yaml")
    capture = open_capture(root)
    rng = np.random.default_rng(seed)
    for fid in capture.frames():
        write_exr(capture.frame_path(fid), rng.random((H, W, 3)) * 4.0)
    return root


def frame(root: Path, fid: str) -> Path:
    g, c, lt = fid.split("/")
    return root / "frames" / g / c / f"{lt}.exr"


# frame id -> (status expected from a header scan, status expected from a deep scan)
PLANTED = {
    "000/cam00/000": ("missing", "missing"),
    "000/cam00/001": ("truncated", "truncated"),
    "000/cam00/002": ("wrong_resolution", "wrong_resolution"),
    "000/cam01/000": ("ok", "non_finite"),
    "000/cam01/001": ("ok", "negative"),
    "000/cam01/002": ("wrong_channels", "wrong_channels"),
    "180/cam00/000": ("unreadable", "unreadable"),
    "180/cam00/001": ("empty", "empty"),
    "180/cam01/000": ("ok", "corrupt"),
}


def plant_problems(root: Path) -> None:
    rng = np.random.default_rng(7)
    frame(root, "000/cam00/000").unlink()
    big = frame(root, "000/cam00/001")
    write_exr(big, rng.random((H, W, 3)), half=False, compression="none")
    data = big.read_bytes()
    big.write_bytes(data[: len(data) - 200])
    write_exr(frame(root, "000/cam00/002"), rng.random((H, W + 2, 3)))
    nan = rng.random((H, W, 3))
    nan[3, 4, 1] = np.nan
    write_exr(frame(root, "000/cam01/000"), nan)
    neg = rng.random((H, W, 3))
    neg[0, 0, 2] = -0.5
    write_exr(frame(root, "000/cam01/001"), neg)
    write_exr(frame(root, "000/cam01/002"), rng.random((H, W, 1)))  # Y only
    frame(root, "180/cam00/000").write_bytes(b"this is not an EXR file\n" * 20)
    frame(root, "180/cam00/001").write_bytes(b"")
    # garbage inside the compressed pixel data: the header and chunk table stay intact
    path = frame(root, "180/cam01/000")
    data = bytearray(path.read_bytes())
    i = int(len(data) * 0.7)
    data[i : i + 40] = b"\xff" * 40
    path.write_bytes(bytes(data))


@pytest.fixture(scope="module")
def bad_capture(tmp_path_factory) -> Path:
    root = make_capture(tmp_path_factory.mktemp("bad") / "cap")
    plant_problems(root)
    return root


def test_statuses_are_documented_in_order():
    assert STATUSES[0] == "ok"
    assert {"missing", "empty", "unreadable", "truncated", "wrong_resolution", "wrong_channels"} <= set(
        STATUSES
    )
    assert {"corrupt", "non_finite", "negative"} <= set(STATUSES)


def test_clean_capture_exit_0(tmp_path, capsys):
    root = make_capture(tmp_path / "cap")
    assert main(["capture", "validate", str(root), "--quiet"]) == 0
    out = capsys.readouterr().out
    assert "12 usable" in out
    manifest = json.loads((root / "validation" / "manifest.json").read_text())
    assert len(manifest["frames"]) == 12
    assert all(f["status"] == "ok" for f in manifest["frames"])
    f0 = manifest["frames"][0]
    assert f0["id"] == "000/cam00/000" and f0["path"] == "frames/000/cam00/000.exr"
    assert f0["resolution"] == [W, H] and f0["dtype"] == "half" and f0["compression"] == "zip"
    assert f0["channels"] == ["B", "G", "R"] and f0["size"] > 0
    assert main(["capture", "validate", str(root), "--deep", "--workers", "2", "--quiet"]) == 0


def test_header_scan_planted_problems(bad_capture, tmp_path, capsys):
    out = tmp_path / "out"
    result = validate_capture(bad_capture, out_dir=out, progress=False)
    got = {r.id: r.status for r in result.records}
    assert len(got) == 12
    for fid, (want, _) in PLANTED.items():
        assert got[fid] == want, (fid, result.records)
    assert not result.ok
    manifest = json.loads((out / "manifest.json").read_text())
    report = json.loads((out / "report.json").read_text())
    assert [f["id"] for f in manifest["frames"]] == [r.id for r in result.records]
    assert report["expected"] == 12 and report["counts"]["missing"] == 1
    assert report["usable"] == 12 - sum(w != "ok" for w, _ in PLANTED.values())
    assert {p["id"] for p in report["problems"]} == {f for f, (w, _) in PLANTED.items() if w != "ok"}
    for p in report["problems"]:  # every message names the file
        assert str(frame(bad_capture, p["id"])) in p["message"], p


def test_deep_scan_planted_problems_and_cli_exit_1(bad_capture, tmp_path, capsys):
    out = tmp_path / "deep"
    code = main(
        ["capture", "validate", str(bad_capture), "--deep", "--workers", "2", "--out", str(out), "--quiet"]
    )
    assert code == 1
    err = capsys.readouterr().err
    assert "missing 1" in err and "non_finite 1" in err
    frames_ = {f["id"]: f for f in json.loads((out / "manifest.json").read_text())["frames"]}
    for fid, (_, want) in PLANTED.items():
        assert frames_[fid]["status"] == want, frames_[fid]
    assert "NaN" in frames_["000/cam01/000"]["message"]
    assert "corrupt EXR pixel data" in frames_["180/cam01/000"]["message"]
    ok = [f for f in frames_.values() if f["status"] == "ok"]
    assert ok and all(f["deep"] and f["saturated_fraction"] is not None for f in ok)


def test_cli_missing_capture_is_one_line_exit_2(tmp_path, capsys):
    assert main(["capture", "validate", str(tmp_path / "nope")]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "does not exist" in err and err.startswith("lightstage: error:")


def test_cli_missing_stage_yaml_exit_2(tmp_path, capsys):
    (tmp_path / "cap").mkdir()
    assert main(["capture", "validate", str(tmp_path / "cap")]) == 2
    assert "stage.yaml" in capsys.readouterr().err


FAKE_WORKER = textwrap.dedent(
    """
    import os, signal, sys, time
    from lightstage.capture import decoder_pool, frame_checks

    def check(request):
        name = os.path.basename(request["path"])
        if name.startswith("crash"):
            os.kill(os.getpid(), signal.SIGSEGV)
        if name.startswith("hang"):
            time.sleep(600)
        return frame_checks.decode_check(request)

    sys.exit(decoder_pool.decoder_main(check))
    """
)


def test_decoder_pool_survives_crash_and_hang(tmp_path):
    script = tmp_path / "fake_worker.py"
    script.write_text(FAKE_WORKER)
    names = ["a.exr", "crash1.exr", "b.exr", "hang.exr", "crash2.exr", "c.exr"]
    for name in names:
        write_exr(tmp_path / name, np.ones((H, W, 3)))
    pool = DecoderPool(workers=2, timeout_s=2.0, command=[sys.executable, str(script)])
    replies = {}
    jobs = [(n, {"path": str(tmp_path / n), "expected": [W, H]}) for n in names]
    pool.run(jobs, lambda k, r: replies.__setitem__(k, r))
    assert set(replies) == set(names)
    for n in ("a.exr", "b.exr", "c.exr"):
        assert replies[n]["status"] == "ok", replies[n]
    for n in ("crash1.exr", "crash2.exr"):
        assert replies[n]["status"] == "corrupt"
        assert f"decoder crashed (signal {int(signal.SIGSEGV)}" in replies[n]["message"]
        assert n in replies[n]["message"]
    assert replies["hang.exr"]["status"] == "corrupt" and "hung" in replies["hang.exr"]["message"]


def test_decoder_that_cannot_start_is_an_error(tmp_path):
    pool = DecoderPool(workers=1, timeout_s=5.0, command=[sys.executable, "-c", "import sys; sys.exit(3)"])
    with pytest.raises(LightstageError, match="failed to start"):
        pool.run([("x", {"path": "x"})], lambda k, r: None)


def test_decode_check_refuses_before_decoding(tmp_path):
    write_exr(tmp_path / "f.exr", np.ones((H, W, 3)))
    reply = decode_check({"path": str(tmp_path / "f.exr"), "expected": [W + 1, H]})
    assert reply["status"] == "corrupt" and "expected 17x12" in reply["message"]


def test_check_pixels():
    img = np.ones((5, 6, 3), np.float16)
    assert check_pixels(img, saturation=4.0).status == "ok"
    img[0, 0, 0] = 5.0
    assert check_pixels(img, saturation=4.0).saturated_fraction == pytest.approx(1 / 30)
    img[1, 1, 1] = -1
    assert check_pixels(img).status == "negative"
    img[2, 2, 2] = np.inf
    res = check_pixels(img)
    assert res.status == "non_finite" and res.non_finite == 1 and res.negative == 1


def test_run_validate_stage(bad_capture, tmp_path):
    work = WorkDir.at(tmp_path / "work")
    work.root.mkdir()
    work.capture_pointer.write_text(str(bad_capture) + "\n")
    # a header scan finds 6 of 12 bad: over a 40 % limit the capture is unusable, under 50 % it is not
    with pytest.raises(LightstageError, match="capture unusable"):
        run_validate(work, ValidateConfig.from_dict({"max_bad_fraction": 0.4}), progress=False)
    assert json.loads(work.report("validate").read_text())["bad"] == 6
    summary = run_validate(work, ValidateConfig.from_dict({"max_bad_fraction": 0.5}), progress=False)
    assert summary["bad"] == 6 and summary["usable"] == 6
    manifest = json.loads(work.manifest.read_text())
    assert len(manifest["frames"]) == 12
    report = json.loads(work.report("validate").read_text())
    assert report["config"]["max_bad_fraction"] == 0.5 and len(report["problems"]) == 6


def test_run_validate_deep_resumes(tmp_path, monkeypatch):
    import lightstage.capture.validate as validate_module

    decoded: list[str] = []

    class CountingPool(DecoderPool):
        def run(self, jobs, on_result):
            jobs = list(jobs)
            decoded.extend(Path(req["path"]).as_posix() for _, req in jobs)
            return super().run(jobs, on_result)

    monkeypatch.setattr(validate_module, "DecoderPool", CountingPool)
    root = make_capture(tmp_path / "cap")
    work = WorkDir.at(tmp_path / "work")
    work.root.mkdir()
    work.capture_pointer.write_text(str(root))
    cfg = ValidateConfig.from_dict({"deep": True, "workers": 1, "max_bad_fraction": 0.2})
    assert run_validate(work, cfg, progress=False)["usable"] == 12
    assert len(decoded) == 12
    # plant a NaN in one frame: only that frame is decoded again and caught
    bad = np.ones((H, W, 3))
    bad[0, 0, 0] = np.nan
    write_exr(frame(root, "180/cam01/002"), bad)
    os.utime(frame(root, "180/cam01/002"), ns=(1, 1))
    summary = run_validate(work, cfg, progress=False)
    assert summary["counts"] == {"ok": 11, "non_finite": 1}
    assert decoded[12:] == [frame(root, "180/cam01/002").as_posix()]


def test_run_validate_errors(tmp_path):
    work = WorkDir.at(tmp_path / "work")
    with pytest.raises(LightstageError, match="capture.txt"):
        run_validate(work, ValidateConfig(), progress=False)
    with pytest.raises(LightstageError, match=r"unknown key 'depp' \(did you mean 'deep'\?\)"):
        ValidateConfig.from_dict({"depp": True})
    with pytest.raises(LightstageError, match="^workers: expected a positive integer or null, got 0"):
        ValidateConfig.from_dict({"workers": 0})
    with pytest.raises(LightstageError, match="max_bad_fraction"):
        ValidateConfig.from_dict({"max_bad_fraction": 2})


def write_layouts(folder: Path) -> list[Path]:
    """Valid EXRs of several layouts: scanline (3 compressions), float, tiled, multipart."""
    import OpenEXR

    rng = np.random.default_rng(5)
    img = rng.random((37, 29, 3)).astype(np.float16)
    paths = []
    for comp in ("zip", "piz", "none"):
        paths.append(folder / f"scan_{comp}.exr")
        write_exr(paths[-1], img, compression=comp)
    paths.append(folder / "float.exr")
    write_exr(paths[-1], img, half=False)
    tiles = OpenEXR.TileDescription()
    tiles.xSize, tiles.ySize = 8, 16
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.tiledimage, "tiles": tiles}
    paths.append(folder / "tiled.exr")
    OpenEXR.File(header, {"RGB": np.ascontiguousarray(img)}).write(str(paths[-1]))
    parts = [
        OpenEXR.Part(
            {"compression": OpenEXR.PIZ_COMPRESSION}, {"RGB": np.ascontiguousarray(img)}, name="rgb"
        ),
        OpenEXR.Part(
            {"compression": OpenEXR.ZIP_COMPRESSION}, {"Z": np.ones((37, 29), np.float32)}, name="z"
        ),
    ]
    paths.append(folder / "multipart.exr")
    OpenEXR.File(parts).write(str(paths[-1]))
    return paths


def test_header_parser_on_valid_layouts_and_every_truncation(tmp_path):
    from lightstage.capture.frame_checks import check_header
    from lightstage.exr_header import read_exr_header
    from lightstage.frames import read_exr

    for path in write_layouts(tmp_path):
        header = read_exr_header(path)
        assert header.chunk_problem is None, (path.name, header.chunk_problem)
        assert (header.width, header.height) == (29, 37) and read_exr(path).shape == (37, 29, 3)
        assert check_header("x", path, path.name, (29, 37)).status == "ok"
        # a file cut anywhere is never reported usable by the header scan
        data = path.read_bytes()
        cut = tmp_path / "cut.exr"
        for n in range(0, len(data), max(1, len(data) // 41)):
            cut.write_bytes(data[:n])
            rec = check_header("x", cut, "cut.exr", (29, 37))
            assert rec.status in ("empty", "unreadable", "truncated"), (path.name, n, rec)


def test_run_validate_on_dask_matches_local(bad_capture, tmp_path):
    distributed = pytest.importorskip("distributed")
    from lightstage.dask_executor import DaskExecutor

    work = WorkDir.at(tmp_path / "work")
    work.root.mkdir()
    work.capture_pointer.write_text(str(bad_capture))
    cfg = ValidateConfig(deep=True, max_bad_fraction=1.0)
    with distributed.Client(
        processes=False, n_workers=1, threads_per_worker=2, dashboard_address=None
    ) as client:
        summary = run_validate(work, cfg, DaskExecutor(client), progress=False)
    frames_ = {f["id"]: f["status"] for f in json.loads(work.manifest.read_text())["frames"]}
    assert len(frames_) == 12 and summary["bad"] == len(PLANTED)
    for fid, (_, want) in PLANTED.items():
        assert frames_[fid] == want
