"""Reading NumPy .npy / .npz files safely from several threads at once.

numpy parses every array header with `ast.literal_eval`, and CPython up to 3.12 keeps the AST constructor's
recursion depth per interpreter, not per thread: two threads parsing at the same moment (a dask worker with two
threads loading statistics) can fail with `SystemError: AST constructor recursion depth mismatch` (seen in the
suite on Python 3.11.7; python/cpython#106905 and the reports linked there). Every load in lightstage goes through
this module, which holds one process-wide lock while numpy parses headers: for an .npy, the open (a memory map's
data is read later, unlocked); for an .npz, the whole read, since the archive parses each member's header when the
member is accessed (so keep .npz files small; tests/test_npyio.py keeps every load here).
"""

from __future__ import annotations

import os
import threading
import zipfile
from collections.abc import Iterable

import numpy as np

_HEADER_LOCK = threading.Lock()


def load_npz(path: str | os.PathLike[str], keys: Iterable[str] | None = None) -> dict[str, np.ndarray]:
    """The arrays of an .npz file (all, or the named `keys`), read into memory; no pickles. A damaged archive
    raises ValueError, as a damaged .npy does, so callers' (OSError, ValueError) handlers name the file
    (zipfile's BadZipFile is neither)."""
    try:
        with _HEADER_LOCK, np.load(path, allow_pickle=False) as z:
            return {k: z[k] for k in (z.files if keys is None else keys)}
    except zipfile.BadZipFile as e:
        raise ValueError(f"not a readable .npz archive ({e})") from None


def load_npy(path: str | os.PathLike[str], mmap_mode: str | None = None) -> np.ndarray:
    """One .npy array, read into memory or memory-mapped (`mmap_mode`, as `np.load`); no pickles."""
    with _HEADER_LOCK:
        return np.load(path, mmap_mode=mmap_mode, allow_pickle=False)
