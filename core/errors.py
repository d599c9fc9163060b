"""The exception types that reach users as a one-line message instead of a traceback, and the line between
content errors (the data is bad: recorded against the item, never retried) and environment errors (the
machine had a moment: the task fails and the executor retries it)."""

from __future__ import annotations

import errno
from collections.abc import Sequence
from typing import Any


class LightstageError(Exception):
    """Bad input or a failed stage: the message names the file or field and the problem."""


class EnvironmentFault(LightstageError):
    """A transient fault of the environment, not of the data (disk full, permission denied, I/O error, a
    temp file that vanished): the task fails and is retried by the executor; it is never recorded as a bad
    frame. Code that records content errors per item must re-raise it (it is a LightstageError so that a
    fault that outlives its retries still ends in one `lightstage: error:` line)."""


class StageIncomplete(LightstageError):
    """A stage ran but could not produce every expected output: the runner exits non-zero, does not record
    the stage as done, and names `missing` in its record so the next run retries exactly that."""

    def __init__(self, message: str, missing: Sequence[str] = (), summary: dict[str, Any] | None = None):
        super().__init__(message)
        self.missing = list(missing)
        self.summary = dict(summary or {})

    def __reduce__(self) -> tuple[Any, ...]:  # keeps `missing` across processes (pool and dask workers)
        return (type(self), (str(self), self.missing, self.summary))


# errno values that describe the machine, not the file's content: retried, never recorded against a frame.
ENVIRONMENT_ERRNOS = frozenset(
    getattr(errno, name)
    for name in (
        "ENOSPC",
        "EDQUOT",
        "EACCES",
        "EPERM",
        "EROFS",
        "EIO",
        "EAGAIN",
        "EBUSY",
        "EINTR",
        "EMFILE",
        "ENFILE",
        "ENOMEM",
        "ESTALE",
        "ETIMEDOUT",
        "ECONNRESET",
        "ENOTCONN",
    )
    if hasattr(errno, name)
)


def is_environment_error(exc: BaseException) -> bool:
    """True for faults worth retrying: an EnvironmentFault, or an OSError with an environment errno (a
    FileNotFoundError counts only for a hidden temporary, which a concurrent cleanup removed)."""
    if isinstance(exc, EnvironmentFault):
        return True
    if isinstance(exc, FileNotFoundError):
        name = str(getattr(exc, "filename", "") or "").rsplit("/", 1)[-1]
        return name.startswith(".") and ".tmp" in name
    return isinstance(exc, OSError) and exc.errno in ENVIRONMENT_ERRNOS
