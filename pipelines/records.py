"""Per-stage run records: what a stage consumed and produced, so a rerun can skip finished stages.

Each stage writes `WORK/reports/<stage>.json` itself; after it returns, the pipeline merges a `pipeline`
section into that file (atomically): config hash, input/output fingerprints, counts, timings, warnings,
errors. Fingerprints are cheap over 60k files: small files are hashed by content, large ones by size and
modification time; hidden files (atomic-write temporaries) are ignored.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from lightstage.atomic import write_json_atomic
from lightstage.workdir import WorkDir

RECORD_KEY = "pipeline"
RECORD_VERSION = 1
CONTENT_HASH_LIMIT = (
    1 << 16
)  # files up to 64 KiB (records, configs) by content; larger (images) by size + mtime


@dataclass(frozen=True)
class Fingerprint:
    """A digest over every file below some paths, with file and byte counts."""

    digest: str
    files: int
    bytes: int

    def to_dict(self) -> dict[str, Any]:
        return {"digest": self.digest, "files": self.files, "bytes": self.bytes}


def _walk(path: Path) -> list[tuple[str, os.stat_result, str]]:
    """(relative name, stat, absolute path) of every non-hidden regular file below `path` (or `path` itself)."""
    out: list[tuple[str, os.stat_result, str]] = []
    if path.is_file():
        return [(path.name, path.stat(), str(path))]
    if not path.is_dir():
        return out
    stack = [(str(path), "")]
    while stack:
        folder, rel = stack.pop()
        try:
            entries = list(os.scandir(folder))
        except OSError:
            continue
        for e in entries:
            if e.name.startswith("."):
                continue
            name = f"{rel}/{e.name}" if rel else e.name
            if e.is_dir(follow_symlinks=False):
                stack.append((e.path, name))
            elif e.is_file():
                out.append((name, e.stat(), e.path))
    return out


def fingerprint(paths: list[Path] | tuple[Path, ...], content_limit: int = CONTENT_HASH_LIMIT) -> Fingerprint:
    """Fingerprint the files below `paths`: names + content hash (small files) or size + mtime (large)."""
    h = hashlib.blake2b(digest_size=16)
    files = 0
    total = 0
    for root in paths:
        root = Path(root)
        h.update(f"@{root.name}\n".encode())
        for name, st, full in sorted(_walk(root)):
            files += 1
            total += st.st_size
            if st.st_size <= content_limit:
                try:
                    with open(full, "rb") as f:
                        tag = hashlib.blake2b(f.read(), digest_size=16).hexdigest()
                except OSError:
                    tag = "unreadable"
            else:
                tag = f"{st.st_size}:{st.st_mtime_ns}"
            h.update(f"{name}\t{tag}\n".encode())
    return Fingerprint(h.hexdigest(), files, total)


def read_report(path: Path) -> dict[str, Any] | None:
    """A stage report as a dict, or None when absent or unreadable (a killed run may have left neither)."""
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    return data if isinstance(data, dict) else None


def report_path(work: WorkDir, stage: str) -> Path:
    """The stage's own report file (WORK/reports/<stage>.json; calibrate writes calibration.json)."""
    from lightstage.pipelines.stages import SPECS

    return work.report(SPECS[stage].report_stem if stage in SPECS else stage)


def read_record(work: WorkDir, stage: str) -> dict[str, Any] | None:
    """The pipeline section of a stage's report, or None."""
    report = read_report(report_path(work, stage))
    record = report.get(RECORD_KEY) if report else None
    return record if isinstance(record, dict) else None


def _list_of_messages(value: Any, limit: int = 20) -> tuple[int, list[str]]:
    if isinstance(value, list):
        return len(value), [v if isinstance(v, str) else json.dumps(v, default=str) for v in value[:limit]]
    if isinstance(value, dict):
        items = list(value.items())
        return len(items), [f"{k}: {v}" for k, v in items[:limit]]
    if isinstance(value, int):
        return value, []
    return 0, []


def summarise_report(report: dict[str, Any] | None, summary: dict[str, Any]) -> dict[str, Any]:
    """Counts, warnings and errors for the record: from the stage's summary, else from its own report."""
    sources = [summary or {}, report or {}]
    out: dict[str, Any] = {}
    for key in ("counts",):
        for src in sources:
            if isinstance(src.get(key), dict):
                out[key] = src[key]
                break
    # Stages name per-item problems differently ("errors", "problems"; a count or a list): take the largest
    # count found, with the messages of a list that has it.
    for key, aliases in (("warnings", ("warnings",)), ("errors", ("errors", "problems"))):
        found = [_list_of_messages(src[a]) for src in sources for a in aliases if a in src]
        n = max((c for c, _ in found), default=0)
        msgs = next((m for c, m in found if c == n and m), [])
        out[key] = n
        out[f"{key}_first"] = msgs
    return out


def write_record(work: WorkDir, stage: str, record: dict[str, Any]) -> None:
    """Merge `record` as the `pipeline` section of WORK/reports/<stage>.json, atomically."""
    path = report_path(work, stage)
    report = read_report(path) or {"stage": stage}
    report[RECORD_KEY] = {"version": RECORD_VERSION, **record}
    write_json_atomic(path, report)


def invalidate(work: WorkDir, stage: str, outputs: tuple[Path, ...]) -> None:
    """Forget a stage: remove its report first (so a kill during removal still reads as "not done"), then
    its outputs."""
    report = report_path(work, stage)
    if report.exists():
        report.unlink()
    for path in outputs:
        if path.is_dir() and not path.is_symlink():
            shutil.rmtree(path)
        elif path.exists() or path.is_symlink():
            path.unlink()


def now_iso() -> str:
    return time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())
