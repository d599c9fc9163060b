"""Capture validation: check every expected frame of a raw capture and write a manifest and a report.

Header checks (pure Python, see exr_header.read_exr_header) run in a thread pool and are fast over 60k files.
`deep` validation also decodes the pixels, in worker *processes* (DecoderPool): a native decoder that crashes
or hangs on a hostile file costs that file only (status `corrupt`), and the scan goes on.
"""

from __future__ import annotations

import json
import os
import sys
import time
from collections import Counter
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from lightstage.atomic import write_json_atomic
from lightstage.capture.decoder_pool import DecoderPool
from lightstage.capture.extra_files import unexpected_files_warning
from lightstage.capture.frame_checks import (
    DEFAULT_TIMEOUT_S,
    LOSSY_COMPRESSIONS,
    STATUSES,
    FrameRecord,
    check_header,
)
from lightstage.capture.layout import Capture, open_capture
from lightstage.config import load, require
from lightstage.errors import LightstageError
from lightstage.executor import Executor, LoopExecutor

MANIFEST_VERSION = 1
MAX_PROBLEMS_LISTED = 1000  # in report.json; the manifest always has every frame


@dataclass
class ValidationResult:
    """Outcome of a scan: one record per expected frame, in capture order, plus how long it took."""

    root: Path
    deep: bool
    records: list[FrameRecord]
    seconds: float = 0.0
    workers: int = 1
    warnings: list[str] = field(default_factory=list)

    @property
    def counts(self) -> dict[str, int]:
        c = Counter(r.status for r in self.records)
        return {s: c.get(s, 0) for s in STATUSES}

    @property
    def problems(self) -> list[FrameRecord]:
        return [r for r in self.records if r.status != "ok"]

    @property
    def ok(self) -> bool:
        """True when every expected frame is usable."""
        return all(r.status == "ok" for r in self.records)

    @property
    def usable(self) -> int:
        return sum(r.status == "ok" for r in self.records)

    def manifest(self, capture: Capture) -> dict[str, Any]:
        return {
            "format_version": MANIFEST_VERSION,
            "capture": str(self.root.resolve()),
            "stage": capture.stage.name,
            "resolution": [capture.stage.width, capture.stage.height],
            "deep": self.deep,
            "created": datetime.now(UTC).isoformat(timespec="seconds"),
            "counts": self.counts,
            "frames": [r.to_dict() for r in self.records],
        }

    def report(self) -> dict[str, Any]:
        problems = self.problems
        n = len(self.records)
        return {
            "stage": "validate",
            "capture": str(self.root.resolve()),
            "deep": self.deep,
            "expected": n,
            "usable": self.usable,
            "bad": len(problems),
            "counts": self.counts,
            "problems": [
                {"id": r.id, "path": r.path, "status": r.status, "message": r.message}
                for r in problems[:MAX_PROBLEMS_LISTED]
            ],
            "problems_listed": min(len(problems), MAX_PROBLEMS_LISTED),
            "warnings": self.warnings,
            "timing": {
                "seconds": round(self.seconds, 3),
                "files_per_s": round(n / self.seconds, 1) if self.seconds > 0 else None,
                "workers": self.workers,
            },
        }

    def summary(self, max_problems: int = 5) -> str:
        """A few lines for the terminal: counts and the first problems."""
        n, bad = len(self.records), self.problems
        head = f"{self.root}: {n} frames expected, {self.usable} usable"
        warnings = [f"  warning: {w}" for w in self.warnings]
        if not bad:
            return "\n".join([head + " (all ok)", *warnings])
        counts = ", ".join(f"{s} {c}" for s, c in self.counts.items() if c and s != "ok")
        lines = [f"{head}; {counts}"]
        lines += [f"  {r.id}: {r.status}: {r.message}" for r in bad[:max_problems]]
        if len(bad) > max_problems:
            lines.append(f"  ... and {len(bad) - max_problems} more (see the report)")
        return "\n".join(lines + warnings)


# --------------------------------------------------------------------------------------------------
# scanning


def default_workers(deep: bool) -> int:
    """Decoder processes for deep scans (one per core); threads for header scans (I/O bound)."""
    cores = os.cpu_count() or 1
    return cores if deep else min(16, 4 * cores)


def check_files(
    items: Sequence[tuple[str, Path, str]],
    expected_size: tuple[int, int] | None = None,
    *,
    deep: bool = False,
    workers: int | None = None,
    saturation: float | None = None,
    timeout_s: float = DEFAULT_TIMEOUT_S,
    progress: bool = True,
    command: Sequence[str] | None = None,
    reuse: dict[str, FrameRecord] | None = None,
) -> list[FrameRecord]:
    """Check (id, absolute path, path to record) items: headers in threads, then (deep) pixels in processes.

    `reuse` maps ids to earlier deep records; a frame whose size and mtime are unchanged is not decoded again.
    """
    from tqdm import tqdm

    threads = workers or default_workers(False)
    with (
        ThreadPoolExecutor(max_workers=threads) as pool,
        tqdm(total=len(items), desc="headers", unit="frame", file=sys.stderr, disable=not progress) as bar,
    ):
        records = []
        for rec in pool.map(lambda it: check_header(it[0], it[1], it[2], expected_size), items):
            records.append(rec)
            bar.update()
    if not deep:
        return records
    jobs = []
    for i, (rec, (_, path, _)) in enumerate(zip(records, items, strict=True)):
        if rec.status != "ok":
            continue
        old = (reuse or {}).get(rec.id)
        if old is not None and old.deep and (old.size, old.mtime_ns) == (rec.size, rec.mtime_ns):
            records[i] = old
            continue
        request = {"path": str(path), "expected": list(expected_size) if expected_size else None}
        request["saturation"] = saturation
        jobs.append((i, request))
    bar = tqdm(total=len(jobs), desc="decode", unit="frame", file=sys.stderr, disable=not progress)

    def done(i: int, reply: dict[str, Any]) -> None:
        rec = records[i]
        rec.deep = True
        rec.status = reply.get("status") if reply.get("status") in STATUSES else "corrupt"
        rec.message = str(reply.get("message", ""))
        if reply.get("saturated_fraction") is not None:
            rec.saturated_fraction = float(reply["saturated_fraction"])
        bar.update()

    with bar:
        DecoderPool(workers or default_workers(True), timeout_s, command).run(jobs, done)
    return records


def capture_items(capture: Capture) -> list[tuple[str, Path, str]]:
    """(id, absolute path, path relative to the capture) of every expected frame, in capture order."""
    items = []
    for fid in capture.frames():
        path = capture.frame_path(fid)
        try:
            rel = path.relative_to(capture.root).as_posix()
        except ValueError:
            rel = str(path)
        items.append((str(fid), path, rel))
    return items


def scan_capture(
    capture: Capture,
    *,
    deep: bool = False,
    workers: int | None = None,
    timeout_s: float = DEFAULT_TIMEOUT_S,
    progress: bool = True,
    executor: Executor | None = None,
    command: Sequence[str] | None = None,
    reuse: dict[str, FrameRecord] | None = None,
) -> ValidationResult:
    """Check every expected frame of an opened capture (writes nothing). In this process (threads for the
    headers, decoder processes for `deep`), or with a parallel `executor` in chunks of frames, one task each."""
    t0 = time.perf_counter()
    items = capture_items(capture)
    expected = (capture.stage.width, capture.stage.height)
    kwargs = dict(deep=deep, saturation=capture.stage.saturation, timeout_s=timeout_s, command=command)
    if executor is None or isinstance(executor, LoopExecutor):
        records = check_files(items, expected, workers=workers, progress=progress, reuse=reuse, **kwargs)
    else:
        records = _check_in_chunks(executor, items, expected, progress, reuse, kwargs)
    result = ValidationResult(
        capture.root, deep, records, time.perf_counter() - t0, workers or default_workers(deep)
    )
    lossy = Counter(r.compression for r in records if r.compression in LOSSY_COMPRESSIONS)
    result.warnings += [f"{n} frames use lossy {c} compression" for c, n in sorted(lossy.items())]
    result.warnings += unexpected_files_warning(capture)
    return result


def _check_in_chunks(
    executor: Executor,
    items: list[tuple[str, Path, str]],
    expected: tuple[int, int],
    progress: bool,
    reuse: dict[str, FrameRecord] | None,
    kwargs: dict[str, Any],
    chunk: int = 512,
) -> list[FrameRecord]:
    """Chunks of frames as executor tasks (a bounded window, 2 per task slot); tasks return record dicts."""
    jobs = []
    for i in range(0, len(items), chunk):
        part = items[i : i + chunk]
        sub_reuse = {k: reuse[k].to_dict() for k, _, _ in part if reuse and k in reuse}
        jobs.append((part, expected, sub_reuse, kwargs))
    out = executor.map(
        _check_chunk,
        jobs,
        desc="validate",
        unit="frame",
        weight=lambda job: len(job[0]),
        window=2 * executor.slots(),
        progress=progress,
    )
    return [FrameRecord.from_dict(r) for recs in out for r in recs]


def _check_chunk(
    job: tuple[list[tuple[str, Path, str]], tuple[int, int], dict[str, dict[str, Any]], dict[str, Any]],
) -> list[dict[str, Any]]:
    """Executor task: check one chunk of frames in the worker, one thread, one decoder process."""
    items, expected, reuse, kwargs = job
    old = {i: FrameRecord.from_dict(d) for i, d in reuse.items()}
    recs = check_files(items, expected, workers=1, progress=False, reuse=old, **kwargs)
    return [r.to_dict() for r in recs]


def write_outputs(
    result: ValidationResult,
    capture: Capture,
    manifest: Path,
    report: Path,
    extra: dict[str, Any] | None = None,
) -> None:
    """Write manifest.json and the report (plus `extra` fields) atomically; a LightstageError if the
    folder is not writable."""
    try:
        write_json_atomic(manifest, result.manifest(capture))
        write_json_atomic(report, {**result.report(), **(extra or {})})
    except OSError as e:
        raise LightstageError(
            f"{e.filename or manifest.parent}: cannot write validation output ({e.strerror or e}); "
            "choose another folder with --out"
        ) from None


def load_manifest_records(path: Path, capture_root: Path) -> dict[str, FrameRecord]:
    """Records of an earlier manifest of the same capture, by frame id ({} when absent, unreadable or of
    another capture)."""
    try:
        data = json.loads(Path(path).read_text())
        if data.get("capture") != str(Path(capture_root).resolve()):
            return {}
        return {d["id"]: FrameRecord.from_dict(d) for d in data.get("frames", [])}
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        return {}


def validate_capture(
    root: str | os.PathLike[str],
    deep: bool = False,
    workers: int | None = None,
    out_dir: str | os.PathLike[str] | None = None,
    progress: bool = True,
    timeout_s: float = DEFAULT_TIMEOUT_S,
) -> ValidationResult:
    """Validate a capture directory; write OUT/manifest.json and OUT/report.json (OUT = CAPTURE/validation).

    A bad capture layout (no stage.yaml, invalid capture.yaml) is a LightstageError; bad frames are not:
    they are in the result (`result.ok` is False).
    """
    capture = open_capture(root)
    out = Path(out_dir) if out_dir is not None else capture.root / "validation"
    reuse = load_manifest_records(out / "manifest.json", capture.root) if deep else None
    result = scan_capture(
        capture, deep=deep, workers=workers, timeout_s=timeout_s, progress=progress, reuse=reuse
    )
    write_outputs(result, capture, out / "manifest.json", out / "report.json")
    return result


# --------------------------------------------------------------------------------------------------
# pipeline stage


@dataclass
class ValidateConfig:
    """Settings of the validate stage."""

    deep: bool = False
    workers: int | None = None  # header threads / decoder processes; None: automatic
    max_bad_fraction: float = 0.05  # more bad frames than this fraction makes the capture unusable
    timeout_s: float = DEFAULT_TIMEOUT_S  # per decoded file

    def __post_init__(self) -> None:
        require(
            self.workers is None or self.workers >= 1,
            "workers",
            f"expected a positive integer or null, got {self.workers!r}",
        )
        require(
            0.0 <= self.max_bad_fraction <= 1.0,
            "max_bad_fraction",
            f"expected a value in [0, 1], got {self.max_bad_fraction!r}",
        )
        require(self.timeout_s > 0, "timeout_s", f"expected a positive number, got {self.timeout_s!r}")

    @classmethod
    def from_dict(cls, d: dict[str, Any] | None) -> ValidateConfig:
        """The strict loader (`lightstage.config`): unknown keys, wrong types and bad values name the key."""
        return load(cls, d)


def run_validate(
    work: Any, config: ValidateConfig, executor: Executor | None = None, progress: bool = True
) -> dict[str, Any]:
    """Pipeline stage: validate the capture named by WORK/capture.txt into WORK/manifest.json and
    WORK/reports/validate.json. A few bad frames are listed (later stages skip them); a LightstageError only
    when the capture is unusable (bad layout, or more than config.max_bad_fraction of the frames bad).

    Resumable: a deep scan reuses the earlier manifest's per-frame results for files whose size and mtime
    are unchanged; header checks always run again (they are cheap and the capture may have been repaired).
    """
    capture = open_capture(work.capture_path())
    reuse = load_manifest_records(work.manifest, capture.root) if config.deep else None
    result = scan_capture(
        capture,
        deep=config.deep,
        workers=config.workers,
        timeout_s=config.timeout_s,
        progress=progress,
        executor=executor,
        reuse=reuse,
    )
    report_path = work.report("validate")
    n, bad = len(result.records), len(result.problems)
    unusable = n == 0 or bad > config.max_bad_fraction * n
    if unusable:
        result.warnings.append(
            f"{bad} of {n} frames are bad, more than max_bad_fraction = {config.max_bad_fraction:g}"
        )
    write_outputs(result, capture, work.manifest, report_path, {"config": asdict(config)})
    if unusable:
        raise LightstageError(
            f"{capture.root}: capture unusable: {bad} of {n} frames are bad "
            f"(limit {config.max_bad_fraction:.1%}); see {report_path}"
        )
    return {
        "expected": n,
        "usable": result.usable,
        "bad": bad,
        "counts": {k: v for k, v in result.counts.items() if v},
        "deep": config.deep,
        "manifest": str(work.manifest),
        "report": str(report_path),
        "seconds": round(result.seconds, 3),
    }
