"""Files in a capture that the capture contract does not account for (docs/capture-format.md): a stray copy,
a frame under a misspelled name, a half-finished transfer. `validate` lists them as a warning, never fails on
them: nothing reads them, but they often mean that the frames someone meant to deliver are not where
capture.yaml says.
"""

from __future__ import annotations

import os
from pathlib import Path

from lightstage.capture.layout import CAPTURE_FILE, STAGE_FILE, Capture
from lightstage.capture.probe import PROBE_FILE, load_probe_info
from lightstage.errors import LightstageError
from lightstage.records.ground_truth import FOLDER as GROUND_TRUTH

# Whole folders a capture may carry: the simulator's ground truth, and validate's default output folder.
KNOWN_FOLDERS = (GROUND_TRUTH, "validation")
# Top-level files besides stage.yaml and capture.yaml: the simulator's preview of the frames.
KNOWN_FILES = ("contact_sheet.png",)
LISTED = 5  # names shown in the warning


def unexpected_files(capture: Capture) -> list[str]:
    """Files under the capture (relative POSIX paths, sorted) that are no expected frame, not stage.yaml or
    capture.yaml, not part of the probe (probe.yaml, its OLAT and ambient frames) and not in KNOWN_FOLDERS."""
    root = capture.root
    probe = _probe_paths(capture)
    skipped = {*KNOWN_FOLDERS, *([] if probe is not None else [Path(PROBE_FILE).parts[0]])}
    expected = {_norm(p, root) for p in [*_contract_paths(capture), *(probe or [])]}
    out = []
    for dirpath, dirnames, filenames in os.walk(root):
        rel_dir = Path(dirpath).relative_to(root)
        if rel_dir == Path("."):
            dirnames[:] = [d for d in dirnames if d not in skipped]
        for name in filenames:
            rel = (rel_dir / name).as_posix()
            if rel not in expected:
                out.append(rel)
    return sorted(out)


def unexpected_files_warning(capture: Capture) -> list[str]:
    """The validate warning for unexpected files: their count and the first few names ([] when none)."""
    extra = unexpected_files(capture)
    if not extra:
        return []
    shown = ", ".join(extra[:LISTED]) + (f", ... ({len(extra) - LISTED} more)" if len(extra) > LISTED else "")
    return [
        f"{len(extra)} unexpected file(s) in the capture (no frame, stage, probe or ground truth): {shown}"
    ]


def _contract_paths(capture: Capture) -> list[Path]:
    """The frames, stage.yaml, capture.yaml, the known top-level files and the views' own masks (where a view
    may have one: masks/<group>/<camera>.png)."""
    root = capture.root
    paths = [capture.frame_path(f) for f in capture.frames()]
    paths += [capture.user_mask(v) for v in capture.views()]
    return [*paths, root / STAGE_FILE, root / CAPTURE_FILE, *(root / n for n in KNOWN_FILES)]


def _probe_paths(capture: Capture) -> list[Path] | None:
    """probe.yaml and the probe's OLAT and ambient frames ([] without a probe); None when probe.yaml cannot
    be read (its folder is then not judged: the probe's own stage reports the file)."""
    root = capture.root
    try:
        probe = load_probe_info(root)
    except LightstageError:
        return None
    if probe is None:
        return []
    paths = [root / PROBE_FILE]
    for pos in probe.positions:
        for cam in capture.stage.camera_ids:
            paths.append(probe.ambient(root, pos, cam))
            paths += [probe.frame(root, pos, cam, lt.index) for lt in capture.stage.lights]
    return paths


def _norm(path: Path, root: Path) -> str:
    """`path` relative to `root`, normalised, as POSIX (a template may hold `./`)."""
    return Path(os.path.normpath(os.path.relpath(path, root))).as_posix()
