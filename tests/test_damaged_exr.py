"""Every file of ../shared/data/exr-damaged (fuzzed / corrupt EXRs from the OpenEXR project) gives a clear
per-file error: no crash, no hang, no multi-GB allocation — through the in-process API and through deep
validation (which decodes in separate processes)."""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from lightstage.capture.decoder_pool import DecoderPool
from lightstage.capture.validate import check_files

pytestmark = pytest.mark.timeout(240)

# Runs in a child process, so a native crash would fail the test instead of killing pytest. It feeds every
# file to read_exr_header, read_exr and read_image and reports what each did, plus the peak memory.
IN_PROCESS_SCRIPT = textwrap.dedent(
    """
    import json, resource, sys
    from pathlib import Path
    from lightstage.frames import read_exr, read_exr_header, read_image
    from lightstage.errors import LightstageError

    def outcome(fn, path):
        try:
            fn(path)
            return {"ok": True}
        except LightstageError as e:
            return {"ok": False, "error": str(e)}
        except BaseException as e:  # anything else is a bug: report it
            return {"ok": False, "unexpected": f"{type(e).__name__}: {e}"}

    for path in sorted(Path(sys.argv[1]).iterdir()):
        if path.suffix == ".rst":
            continue
        rec = {"name": path.name}
        for label, fn in (("header", read_exr_header), ("read", read_exr), ("image", read_image)):
            rec[label] = outcome(fn, path)
        print(json.dumps(rec), flush=True)
    # This process's own peak: VmHWM of its address space. (ru_maxrss also counts the parent's resident memory
    # before exec: Linux carries it over when subprocess spawns with vfork, so it read ~1.1 GB in a busy pytest.)
    status = Path("/proc/self/status")
    hwm = [ln for ln in status.read_text().splitlines() if ln.startswith("VmHWM:")] if status.exists() else []
    peak_kb = int(hwm[0].split()[1]) if hwm else resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    print(json.dumps({"maxrss_mb": peak_kb / 1024}))
    """
)

# A decoder process that hands each file straight to OpenEXR, without the header checks of read_exr, to
# show that even an unchecked native decode on these files costs only the file (never the scan).
RAW_DECODER_SCRIPT = textwrap.dedent(
    """
    import sys
    import OpenEXR
    from lightstage.capture import decoder_pool

    def raw(request):
        try:
            f = OpenEXR.File(request["path"], separate_channels=True)
            n = sum(c.pixels.size for c in f.parts[0].channels.values())
            return {"status": "ok", "message": f"decoded {n} samples"}
        except Exception as e:
            return {"status": "corrupt", "message": f"{request['path']}: {type(e).__name__}: {e}"}

    sys.exit(decoder_pool.decoder_main(raw))
    """
)


def damaged_files(shared_data: Path) -> list[Path]:
    folder = shared_data / "exr-damaged"
    if not folder.is_dir():
        pytest.skip(f"{folder} is absent")
    files = sorted(p for p in folder.iterdir() if p.is_file() and p.suffix != ".rst")
    assert files
    return files


def test_in_process_api_refuses_every_damaged_file(shared_data):
    files = damaged_files(shared_data)
    proc = subprocess.run(
        [sys.executable, "-c", IN_PROCESS_SCRIPT, str(files[0].parent)],
        capture_output=True,
        text=True,
        timeout=180,
    )
    assert proc.returncode == 0, f"child died ({proc.returncode}): {proc.stderr[-2000:]}"
    lines = [json.loads(line) for line in proc.stdout.splitlines()]
    records, peak = lines[:-1], lines[-1]["maxrss_mb"]
    assert [r["name"] for r in records] == [p.name for p in files]
    for rec in records:
        for label in ("header", "read", "image"):
            res = rec[label]
            assert "unexpected" not in res, (rec["name"], label, res)
            if label != "header":  # a header may parse; the pixels of every file are refused
                assert not res["ok"], (rec["name"], label)
            if not res["ok"]:
                assert rec["name"] in res["error"], (rec["name"], label, res)
    assert peak < 1024, f"peak memory {peak:.0f} MB"


def test_deep_validation_marks_every_damaged_file(shared_data):
    files = damaged_files(shared_data)
    items = [(p.name, p, p.name) for p in files]
    records = check_files(items, None, deep=True, workers=2, timeout_s=30, progress=False)
    assert [r.id for r in records] == [p.name for p in files]
    for rec in records:
        assert rec.status not in ("ok", "missing"), rec
        assert rec.id in rec.message, rec
    # with the stage's resolution expected, nothing gets near a decoder that is not the right size either
    records = check_files(items, (8192, 5464), deep=False, workers=4, progress=False)
    assert all(r.status != "ok" and r.id in r.message for r in records)


def test_unchecked_native_decode_is_isolated(shared_data, tmp_path):
    files = damaged_files(shared_data)
    script = tmp_path / "raw_decoder.py"
    script.write_text(RAW_DECODER_SCRIPT)
    replies: dict[str, dict] = {}
    pool = DecoderPool(workers=2, timeout_s=30, command=[sys.executable, str(script)], memory_limit_mb=4096)
    pool.run([(p.name, {"path": str(p)}) for p in files], lambda k, r: replies.__setitem__(k, r))
    assert set(replies) == {p.name for p in files}
    for name, reply in replies.items():
        assert reply["status"] == "corrupt", (name, reply)
        assert name in reply["message"], (name, reply)
