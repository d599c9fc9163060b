"""Decoder processes of deep validation: a native decoder that crashes or hangs on a hostile file costs that
file only (status `corrupt`), and the scan goes on. Each process talks JSON lines over stdin/stdout and runs
`frame_checks.decode_check`; `python -m lightstage.capture.decoder_pool --decode-worker` is one such process."""

from __future__ import annotations

import json
import os
import selectors
import signal
import subprocess
import sys
import tempfile
import time
from collections import deque
from collections.abc import Callable, Iterable, Sequence
from typing import Any

from lightstage.capture.frame_checks import DEFAULT_MEMORY_LIMIT_MB, DEFAULT_TIMEOUT_S, decode_check
from lightstage.errors import LightstageError

# --------------------------------------------------------------------------------------------------
# decoder processes


def decoder_command() -> list[str]:
    """The command that starts one decoder process (this module with --decode-worker)."""
    return [sys.executable, "-m", "lightstage.capture.decoder_pool", "--decode-worker"]


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


if __name__ == "__main__":
    if sys.argv[1:] == ["--decode-worker"]:
        sys.exit(decoder_main())
    sys.exit(
        "usage: python -m lightstage.capture.decoder_pool --decode-worker (internal; use `lightstage capture validate`)"
    )
