"""`capture validate` lists files that no frame, stage.yaml, capture.yaml, the probe or the ground truth account
for as a warning (count and first names) and does not fail on them (capture/extra_files.py)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

from lightstage.capture.extra_files import LISTED, unexpected_files
from lightstage.capture.layout import open_capture
from lightstage.pipelines.cli import main as cli_main


def test_simulated_capture_has_no_unexpected_files(tiny_capture: Path) -> None:
    capture = open_capture(tiny_capture)
    assert unexpected_files(capture) == []
    # the probe and the ground truth were there to be accounted for
    assert any((tiny_capture / "ground_truth").rglob("*.json")) and any(
        (tiny_capture / "probe").rglob("*.exr")
    )


def test_unexpected_files_are_a_warning_naming_the_first_few(
    tiny_capture: Path, tmp_path: Path, capsys
) -> None:
    root = tmp_path / "capture"
    shutil.copytree(tiny_capture, root)
    planted = sorted(
        [
            "notes.txt",
            ".DS_Store",
            "frames/000/cam00/000.exr.bak",
            "frames/000/cam00/12.exr",  # a frame under a name capture.yaml's template does not give
            "frames/040/stray.exr",
            "old/frames/000/cam00/000.exr",
            "probe/extra.txt",
        ]
    )
    for rel in planted:
        (root / rel).parent.mkdir(parents=True, exist_ok=True)
        (root / rel).write_bytes(b"x")
    assert unexpected_files(open_capture(root)) == planted

    assert cli_main(["capture", "validate", str(root), "--quiet"]) == 0  # a warning, not a failure
    out = capsys.readouterr().out
    shown = ", ".join(planted[:LISTED])
    warning = (
        f"{len(planted)} unexpected file(s) in the capture (no frame, stage, probe or ground truth): {shown}"
    )
    assert f"  warning: {warning}, ... ({len(planted) - LISTED} more)" in out
    report = json.loads((root / "validation" / "report.json").read_text())
    assert report["usable"] == report["expected"] and any(w.startswith(warning) for w in report["warnings"])
    # validate's own output folder (now in the capture) is not unexpected
    assert unexpected_files(open_capture(root)) == planted
