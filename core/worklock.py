"""One exclusive lock per work directory, so two `lightstage` commands never write one WORK at once.

`hold_work_lock(WORK, command)` takes `fcntl.flock(LOCK_EX | LOCK_NB)` on WORK/.lock and writes who holds it
(pid, host, command, start time) into the file; a second command fails at once with a `WorkLocked` naming the
holder. The kernel drops a flock when its holder dies (kill -9 included), so a dead run's lock is simply taken
over; the file is never deleted (unlinking a lock file races with a process that has it open) and is left empty
when its holder exits. Because the holder is the only live writer, it may remove the temporaries that killed
runs left behind (`lightstage.atomic.remove_stale_temps`), which it does right after taking the lock.

Only the CLI's dispatch takes the lock (pipelines/cli.py); dask workers, torchrun ranks and other subprocesses
of the holder work under it without taking it. flock works on local file systems and on NFS (Linux >= 2.6.12
emulates it with byte-range locks), so a second host sharing WORK is refused too.
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import os
import socket
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path

from lightstage.atomic import remove_stale_temps
from lightstage.errors import LightstageError
from lightstage.records.shards import MANIFEST as SHARD_MANIFEST
from lightstage.workdir import WorkDir

LOCK_NAME = ".lock"
_HELD: dict[Path, int] = {}  # work directories this process holds, with a nesting count


class WorkLocked(LightstageError):
    """Another live process holds the work directory's lock."""


@dataclass(frozen=True)
class Holder:
    """Who holds a work directory: what the lock file records."""

    pid: int
    host: str
    command: str
    started: str  # ISO 8601, local time with its offset

    def describe(self) -> str:
        """'pid 123 on host, `lightstage run ...`, since 2025-01-01T10:00:00+00:00' (one line)."""
        return f"pid {self.pid} on {self.host}, `{self.command}`, since {self.started}"


@dataclass
class WorkLock:
    """A held lock: who we are and which stale temporaries were removed on taking it."""

    root: Path
    holder: Holder
    removed: list[Path] = field(default_factory=list)


def lock_path(root: str | os.PathLike[str]) -> Path:
    """WORK/.lock."""
    return Path(root) / LOCK_NAME


@contextlib.contextmanager
def hold_work_lock(root: str | os.PathLike[str], command: str, *, create: bool = True) -> Iterator[WorkLock]:
    """Hold WORK's lock for the `with` body: create WORK when `create` (else it must exist), take the lock
    or raise WorkLocked naming the holder, then remove the leftovers of killed runs. Re-entrant within one
    process."""
    root = Path(root)
    _check_dir(root, create)
    key = root.resolve()
    if key in _HELD:  # this process already holds it (a command run from inside another)
        _HELD[key] += 1
        try:
            yield WorkLock(root, _me(command))
        finally:
            _HELD[key] -= 1
        return
    path = lock_path(root)
    try:
        fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o666)
    except OSError as e:
        raise LightstageError(f"{path}: cannot open the work directory's lock ({e.strerror or e})") from None
    try:
        _acquire(fd, root, path)
        me = _me(command)
        _record(fd, me)
        _HELD[key] = 1
        try:
            yield WorkLock(root, me, remove_leftovers(WorkDir(root)))
        finally:
            del _HELD[key]
            with contextlib.suppress(OSError):
                os.ftruncate(fd, 0)  # an idle work directory's lock file is empty
    finally:
        os.close(fd)  # releases the flock


def remove_leftovers(work: WorkDir) -> list[Path]:
    """Temporaries of killed writers anywhere in WORK (never inside a raw capture kept there, as the demo
    does), and shards/tmp once the shard manifest exists (before that it is the interrupted shard's resume
    state, which the next shard run uses and removes). Call only while holding the lock."""
    try:
        capture = work.capture_pointer.read_text().strip() or None
    except OSError:
        capture = None
    scratch = [(work.shards_dir / "tmp", work.shards_dir / SHARD_MANIFEST)]  # dataset/shards.py's scratch
    return remove_stale_temps(work.root, skip=capture, scratch=scratch)


def read_holder(root: str | os.PathLike[str]) -> Holder | None:
    """What WORK/.lock says about its holder (None when empty or unreadable); says nothing about liveness."""
    try:
        return _parse(lock_path(root).read_bytes())
    except OSError:
        return None


def _check_dir(root: Path, create: bool) -> None:
    """WORK must be a directory; created (with its parents) when `create`."""
    if root.exists() and not root.is_dir():
        raise LightstageError(f"{root}: not a directory (the work directory must be a folder)")
    if root.is_dir():
        return
    if not create:
        raise LightstageError(
            f"{root}: work directory not found (make one with: lightstage run CAPTURE --work {root})"
        )
    try:
        root.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise LightstageError(f"{root}: cannot create the work directory ({e.strerror or e})") from None


def _acquire(fd: int, root: Path, path: Path) -> None:
    """flock(LOCK_EX | LOCK_NB) or a WorkLocked naming the holder."""
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        return
    except BlockingIOError:
        pass
    except OSError as e:  # ENOLCK: a file system without locks
        raise LightstageError(f"{path}: cannot lock the work directory ({e.strerror or e})") from None
    holder = None
    for _ in range(20):  # the holder writes its record right after locking: give it a moment
        holder = _parse(os.pread(fd, 4096, 0))
        if holder is not None:
            break
        time.sleep(0.05)
    who = holder.describe() if holder is not None else "a process that has not recorded itself yet"
    raise WorkLocked(
        f"{root}: work directory in use by another lightstage command ({who}); wait for it to finish "
        "or stop it (a killed command's lock is released at once)"
    )


def _me(command: str) -> Holder:
    started = datetime.now().astimezone().isoformat(timespec="seconds")
    return Holder(os.getpid(), socket.gethostname(), command[:300], started)


def _record(fd: int, holder: Holder) -> None:
    """Write the holder's record into the lock file (best effort: the lock holds without it)."""
    data = json.dumps(holder.__dict__).encode() + b"\n"
    with contextlib.suppress(OSError):
        os.ftruncate(fd, 0)
        os.pwrite(fd, data, 0)


def _parse(data: bytes) -> Holder | None:
    try:
        d = json.loads(data)
        return Holder(int(d["pid"]), str(d["host"]), str(d["command"]), str(d["started"]))
    except (ValueError, KeyError, TypeError):
        return None
