"""Atomic file writes: a temp file in the destination folder, then os.replace, so a killed run never
leaves a partial output where a finished one is expected."""

from __future__ import annotations

import contextlib
import json
import os
import re
import shutil
import tempfile
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any

# The names atomic_path gives its temporaries: `.<stem>.<8 random chars>.tmp<suffix>` (tempfile.mkstemp).
TEMP_NAME = re.compile(r"^\..*\.[a-z0-9_]{8}\.tmp(\.[^.]+)?$")


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike[str]) -> Iterator[Path]:
    """Yield a temporary path beside `path` (same suffix); on success it is renamed onto `path`. An OSError
    that names no file (a buffered write to a full disk) is re-raised naming `path`, errno kept."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    # the writer's pid in the name: a cleanup can tell a live writer's temp from a dead one's (temp_owner)
    fd, tmp = tempfile.mkstemp(
        prefix=f".{path.stem}.{os.getpid()}.", suffix=f".tmp{path.suffix}", dir=path.parent
    )
    # mkstemp creates 0600; give the file the permissions a plain open() would (0666 minus the umask)
    os.fchmod(fd, 0o666 & ~_current_umask())
    os.close(fd)
    tmp_path = Path(tmp)
    try:
        yield tmp_path
        os.replace(tmp_path, path)
    except OSError as e:
        if e.filename is None and e.errno is not None:
            raise OSError(e.errno, e.strerror or str(e), os.fspath(path)) from e
        raise
    finally:
        if tmp_path.exists():
            tmp_path.unlink()


def _current_umask() -> int:
    """The process umask (reading it requires setting it; restored at once)."""
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def write_bytes_atomic(path: str | os.PathLike[str], data: bytes) -> None:
    """Write `data` to `path` atomically."""
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)


def write_text_atomic(path: str | os.PathLike[str], text: str) -> None:
    """Write `text` (UTF-8) to `path` atomically."""
    write_bytes_atomic(path, text.encode("utf-8"))


def write_json_atomic(path: str | os.PathLike[str], obj: Any) -> None:
    """Write `obj` as indented JSON to `path` atomically."""
    write_text_atomic(path, json.dumps(obj, indent=2, sort_keys=False, default=_json_default) + "\n")


def _json_default(obj: Any) -> Any:
    import numpy as np

    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, os.PathLike):
        return os.fspath(obj)
    raise TypeError(f"not JSON serialisable: {type(obj).__name__}")


def temp_owner(name: str) -> int | None:
    """The pid of the process that made an atomic_path temporary (`.<stem>.<pid>.<random>.tmp<suffix>`);
    None for a name without one (written before pids were in the names)."""
    parts = name.split(".")
    i = next((k for k in range(len(parts) - 1, 0, -1) if parts[k] == "tmp"), None)
    if i is None or i < 4 or not parts[i - 2].isdigit():
        return None
    return int(parts[i - 2])


def is_temp_name(name: str) -> bool:
    """Whether a file name is one of atomic_path's temporaries."""
    return TEMP_NAME.match(name) is not None


def remove_stale_temps(
    root: str | os.PathLike[str],
    *,
    skip: str | os.PathLike[str] | None = None,
    scratch: Iterable[tuple[Path, Path]] = (),
) -> list[Path]:
    """Remove what killed writers left below `root`: atomic_path temporaries (not under `skip`), and each
    (folder, marker) scratch folder whose marker file exists (its work finished; without the marker it is
    resume state). Safe only for the holder of root's work lock (lightstage.worklock): no live writer can
    own them then. Returns what was removed."""
    root, removed = Path(root), []
    skip_dir = Path(skip).resolve() if skip is not None else None
    for folder, marker in scratch:
        if folder.is_dir() and marker.is_file():
            shutil.rmtree(folder, ignore_errors=True)
            removed.append(folder)
    for dirpath, dirnames, filenames in os.walk(root):
        if skip_dir is not None:
            dirnames[:] = [d for d in dirnames if Path(dirpath, d).resolve() != skip_dir]
        for name in filenames:
            if is_temp_name(name):
                path = Path(dirpath, name)
                with contextlib.suppress(FileNotFoundError):
                    path.unlink()
                    removed.append(path)
    return removed
