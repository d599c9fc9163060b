"""Capture validation: check every expected frame of a raw capture and write a manifest and a report.

Header checks (pure Python, see frames.read_exr_header) run in a thread pool and are fast over 60k files.
`deep` validation also decodes the pixels, in worker *processes* (DecoderPool): a native decoder that crashes
or hangs on a hostile file costs that file only (status `corrupt`), and the scan goes on.
"""

from __future__ import annotations

import json
import os
import selectors
import signal
import stat
import subprocess
import sys
import tempfile
import time
from collections import Counter, deque
from collections.abc import Callable, Iterable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass, field, fields
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from lightstage import frames
from lightstage.atomic import write_json_atomic
from lightstage.capture.extra_files import unexpected_files_warning
from lightstage.capture.layout import Capture, open_capture
from lightstage.config import load, require
from lightstage.errors import LightstageError
from lightstage.executor import Executor, LoopExecutor

# Every status a frame can get; only `ok` frames are usable.
STATUSES = (
    "ok",
    "missing",  # no file where capture.yaml's template says
    "empty",  # zero bytes
    "unreadable",  # not an EXR, corrupt/unsupported header (deep data, absurd sizes)
    "truncated",  # the chunk table points past the end of the file, or chunks were never written
    "wrong_resolution",  # data window differs from the stage's raw resolution
    "wrong_channels",  # no R, G, B of one half/float type
    "corrupt",  # deep only: pixel decode failed, the decoder crashed or hung
    "non_finite",  # deep only: NaN or Inf samples
    "negative",  # deep only: negative samples
)
DEEP_STATUSES = ("corrupt", "non_finite", "negative")
LOSSY_COMPRESSIONS = ("b44", "b44a", "dwaa", "dwab", "htj2k256", "htj2k32", "lj2k")
MANIFEST_VERSION = 1
DEFAULT_TIMEOUT_S = 300.0  # per decoded file; a full 8192x5464 frame decodes in ~0.3 s
DEFAULT_MEMORY_LIMIT_MB = 8192  # address-space ceiling of each decoder process
MAX_PROBLEMS_LISTED = 1000  # in report.json; the manifest always has every frame


@dataclass
class FrameRecord:
    """One expected frame in the manifest: where it is, what its header says, and its status."""

    id: str
    path: str
    status: str = "ok"
    message: str = ""
    size: int = 0
    mtime_ns: int = 0
    dtype: str = ""
    width: int = 0
    height: int = 0
    channels: list[str] = field(default_factory=list)
    compression: str = ""
    deep: bool = False  # pixels were decoded and checked
    saturated_fraction: float | None = None  # deep only: fraction of pixels at/above the stage cutoff

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["resolution"] = [d.pop("width"), d.pop("height")]
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> FrameRecord:
        """A record this module wrote (`to_dict`), not user input: read as it is, keys it does not know are
        left out (the strict config loader is for configs; this runs once per frame of a 60k-frame scan)."""
        d = dict(d)
        d["width"], d["height"] = d.pop("resolution", [0, 0])
        names = {f.name for f in fields(cls)}
        return cls(**{k: v for k, v in d.items() if k in names})

    def fail(self, status: str, message: str) -> FrameRecord:
        self.status, self.message = status, message
        return self


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
# per-frame checks


def check_header(frame_id: str, path: Path, rel: str, expected_size: tuple[int, int] | None) -> FrameRecord:
    """Header-only checks of one file (no pixel decoding, no native code): never raises."""
    rec = FrameRecord(frame_id, rel)
    try:
        st = path.stat()
    except FileNotFoundError:
        return rec.fail("missing", f"{path}: file not found")
    except OSError as e:
        return rec.fail("unreadable", f"{path}: cannot stat ({e.strerror or e})")
    rec.size, rec.mtime_ns = st.st_size, st.st_mtime_ns
    if not stat.S_ISREG(st.st_mode):
        return rec.fail("unreadable", f"{path}: not a regular file")
    if st.st_size == 0:
        return rec.fail("empty", f"{path}: empty file")
    try:
        header = frames.read_exr_header(path)
    except LightstageError as e:
        return rec.fail("unreadable", str(e))
    except Exception as e:  # a bug in the parser must cost one file, not the scan
        return rec.fail("unreadable", f"{path}: cannot parse header ({type(e).__name__}: {e})")
    rec.width, rec.height = header.width, header.height
    rec.channels = list(header.channels)
    rec.compression = header.compression
    rec.dtype = header.rgb_dtype() or header.dtype
    if header.chunk_problem:
        cut = header.chunk_problem.startswith(("truncated", "incomplete"))
        return rec.fail("truncated" if cut else "unreadable", f"{path}: {header.chunk_problem}")
    if frames.oversized(header.width, header.height) or (
        expected_size is not None and (header.width, header.height) != tuple(expected_size)
    ):
        want = f"expected {expected_size[0]}x{expected_size[1]}" if expected_size else "over the pixel limit"
        return rec.fail("wrong_resolution", f"{path}: resolution {header.width}x{header.height}, {want}")
    try:
        frames.check_exr_header(header, expected_size, "RGB")
    except LightstageError as e:
        status = "unreadable" if header.decode_bytes > frames.MAX_DECODE_BYTES else "wrong_channels"
        return rec.fail(status, str(e))
    return rec


def decode_check(request: dict[str, Any]) -> dict[str, Any]:
    """Decode one frame and check its pixels (runs inside a decoder process); returns a small dict."""
    path = request["path"]
    expected = tuple(request["expected"]) if request.get("expected") else None
    try:
        pixels = frames.read_exr(path, expected_size=expected, channels="RGB")  # header re-checked first
    except LightstageError as e:
        return {"status": "corrupt", "message": str(e)}
    except MemoryError:
        return {"status": "corrupt", "message": f"{path}: out of memory while decoding"}
    result = frames.check_pixels(pixels, request.get("saturation"))
    message = f"{path}: {result.message}" if result.message else ""
    return {"status": result.status, "message": message, "saturated_fraction": result.saturated_fraction}


# --------------------------------------------------------------------------------------------------
# decoder processes


def decoder_command() -> list[str]:
    """The command that starts one decoder process (this module with --decode-worker)."""
    return [sys.executable, "-m", "lightstage.capture.validate", "--decode-worker"]


class _Worker:
    """One decoder process, talking JSON lines over its stdin/stdout."""

    def __init__(self, command: Sequence[str], memory_limit_mb: int | None):
        # append mode: the child always writes at the end, so reading with pread never moves its offset
        self.stderr = tempfile.TemporaryFile(mode="a+b")
        self.err_mark = 0
        env = dict(os.environ)
        if memory_limit_mb:
            env["LIGHTSTAGE_DECODER_MEMORY_MB"] = str(int(memory_limit_mb))
        self.proc = subprocess.Popen(
            list(command), stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=self.stderr, env=env
        )
        self.buf = b""
        self.ready = False
        self.job: tuple[Any, dict[str, Any]] | None = None
        self.deadline = time.monotonic()

    def send(self, key: Any, request: dict[str, Any], timeout_s: float) -> None:
        self.job = (key, request)
        self.deadline = time.monotonic() + timeout_s
        self.err_mark = os.fstat(self.stderr.fileno()).st_size
        assert self.proc.stdin is not None
        self.proc.stdin.write((json.dumps(request) + "\n").encode())
        self.proc.stdin.flush()

    def stderr_tail(self) -> str:
        """The last line the process wrote to stderr."""
        lines = os.pread(self.stderr.fileno(), 1 << 16, 0).decode("utf-8", "replace").strip().splitlines()
        return lines[-1][:300] if lines else ""

    def job_diagnostic(self) -> str:
        """The decoder library's own error for the current job (what it printed to stderr), if any."""
        fd = self.stderr.fileno()
        n = os.fstat(fd).st_size - self.err_mark
        text = os.pread(fd, min(n, 1 << 16), self.err_mark).decode("utf-8", "replace") if n > 0 else ""
        lines = [ln.strip() for ln in text.splitlines() if ln.strip()]
        useful = [ln for ln in lines if "EXR_ERR" in ln] or lines
        return useful[0][:300] if useful else ""

    def stop(self, kill: bool = False) -> int:
        if kill and self.proc.poll() is None:
            self.proc.kill()
        for stream in (self.proc.stdin, self.proc.stdout):
            try:
                if stream is not None:
                    stream.close()
            except OSError:
                pass
        try:
            rc = self.proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            rc = self.proc.wait()
        self.stderr.close()
        return rc


class DecoderPool:
    """Decode frames in `workers` separate processes, one file at a time each.

    A process that dies (segfault, abort) or exceeds `timeout_s` on a file is replaced; that file gets status
    `corrupt` with "decoder crashed (signal N)" / "decoder hung", and the other files carry on.
    """

    STARTUP_TIMEOUT_S = 120.0
    MAX_START_FAILURES = 3

    def __init__(
        self,
        workers: int,
        timeout_s: float = DEFAULT_TIMEOUT_S,
        command: Sequence[str] | None = None,
        memory_limit_mb: int | None = DEFAULT_MEMORY_LIMIT_MB,
    ):
        self.workers = max(1, int(workers))
        self.timeout_s = float(timeout_s)
        self.command = list(command or decoder_command())
        self.memory_limit_mb = memory_limit_mb

    def run(
        self,
        jobs: Iterable[tuple[Any, dict[str, Any]]],
        on_result: Callable[[Any, dict[str, Any]], None],
    ) -> None:
        """Run every (key, request) job; on_result(key, reply) is called once per job, in completion order."""
        pending = deque(jobs)
        if not pending:
            return
        sel = selectors.DefaultSelector()
        live: list[_Worker] = []
        start_failures = 0

        def spawn() -> None:
            w = _Worker(self.command, self.memory_limit_mb)
            w.deadline = time.monotonic() + self.STARTUP_TIMEOUT_S
            assert w.proc.stdout is not None
            os.set_blocking(w.proc.stdout.fileno(), False)
            sel.register(w.proc.stdout, selectors.EVENT_READ, w)
            live.append(w)

        def retire(w: _Worker, kill: bool, why: str | None) -> None:
            nonlocal start_failures
            assert w.proc.stdout is not None
            sel.unregister(w.proc.stdout)
            live.remove(w)
            tail = w.stderr_tail()
            diagnostic = w.job_diagnostic() if w.job is not None else ""
            rc = w.stop(kill=kill)
            if w.job is not None:
                key, req = w.job
                detail = f" [decoder: {diagnostic}]" if diagnostic and not why else ""
                on_result(
                    key, {"status": "corrupt", "message": f"{req['path']}: {why or _death(rc)}{detail}"}
                )
            elif not w.ready:
                start_failures += 1
                if start_failures >= self.MAX_START_FAILURES:
                    for other in list(live):
                        other.stop(kill=True)
                    raise LightstageError(
                        f"decoder process failed to start ({_death(rc)}): {tail or ' '.join(self.command)}"
                    )
            if pending and len(live) < self.workers:
                spawn()

        for _ in range(min(self.workers, len(pending))):
            spawn()
        try:
            while live:
                for w in list(live):
                    if w.ready and w.job is None and pending:
                        job = pending.popleft()
                        try:
                            w.send(*job, self.timeout_s)
                        except OSError:  # died while idle: not this file's fault, give it to another
                            w.job = None
                            pending.appendleft(job)
                            retire(w, kill=True, why=None)
                idle = [w for w in live if w.ready and w.job is None]
                if not pending and len(idle) == len(live):
                    break
                now = time.monotonic()
                busy = [w for w in live if w.job is not None or not w.ready]
                wait = max(0.0, min(w.deadline for w in busy) - now) if busy else None
                for key, _ in sel.select(timeout=wait):
                    w = key.data
                    try:
                        chunk = os.read(key.fd, 65536)
                    except BlockingIOError:
                        continue
                    if not chunk:
                        retire(w, kill=False, why=None)
                        continue
                    w.buf += chunk
                    while b"\n" in w.buf:
                        line, w.buf = w.buf.split(b"\n", 1)
                        reply = _parse_reply(line)
                        if not w.ready:
                            w.ready = True
                            start_failures = 0
                        elif w.job is not None:
                            job_key, _req = w.job
                            if reply.get("status") == "corrupt" and (detail := w.job_diagnostic()):
                                reply["message"] = f"{reply.get('message', '')} [decoder: {detail}]"
                            w.job = None
                            on_result(job_key, reply)
                now = time.monotonic()
                for w in list(live):
                    if (w.job is not None or not w.ready) and now > w.deadline:
                        why = f"decoder hung (no result after {self.timeout_s:g} s)" if w.job else None
                        retire(w, kill=True, why=why)
        finally:
            for w in list(live):
                w.stop(kill=False)
            sel.close()


def _parse_reply(line: bytes) -> dict[str, Any]:
    try:
        reply = json.loads(line)
    except ValueError:
        return {"status": "corrupt", "message": f"garbled decoder reply {line[:80]!r}"}
    return reply if isinstance(reply, dict) else {"status": "corrupt", "message": "garbled decoder reply"}


def _death(rc: int | None) -> str:
    if rc is not None and rc < 0:
        try:
            name = signal.Signals(-rc).name
        except ValueError:
            name = "unknown"
        return f"decoder crashed (signal {-rc}, {name})"
    return f"decoder process exited with code {rc}"


def decoder_main(check: Callable[[dict[str, Any]], dict[str, Any]] = decode_check) -> int:
    """Body of a decoder process: read JSON requests on stdin, answer one JSON line each on stdout."""
    protocol = os.fdopen(os.dup(1), "w", buffering=1)
    os.dup2(2, 1)  # stray prints from native libraries must not corrupt the protocol
    limit_mb = int(os.environ.get("LIGHTSTAGE_DECODER_MEMORY_MB", "0") or 0)
    if limit_mb > 0:
        import resource

        resource.setrlimit(resource.RLIMIT_AS, (limit_mb << 20, limit_mb << 20))
    import OpenEXR

    OpenEXR.set_global_thread_count(1)  # processes scale the work; one library thread each
    protocol.write('{"ready": true}\n')
    for line in sys.stdin:
        if not line.strip():
            continue
        request = json.loads(line)
        try:
            reply = check(request)
        except Exception as e:
            reply = {"status": "corrupt", "message": f"{request.get('path')}: {type(e).__name__}: {e}"}
        protocol.write(json.dumps(reply) + "\n")
    return 0


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


if __name__ == "__main__":
    if sys.argv[1:] == ["--decode-worker"]:
        sys.exit(decoder_main())
    sys.exit(
        "usage: python -m lightstage.capture.validate --decode-worker (internal; use `lightstage capture validate`)"
    )
