"""The on/off switch of an optional numba kernel path (the hash grid's lookups, the downscale): read once
from an environment variable, flipped by tests and benches that compare it with the plain path."""

from __future__ import annotations

import os


class KernelSwitch:
    """`available()` is True when the kernels import (`importable`) and are not switched off, either by the
    environment (`env` set to `off_value`) or by `set_enabled(False)`."""

    def __init__(self, env: str, off_value: str, importable: bool) -> None:
        self.env, self.off_value, self.importable = env, off_value, importable
        self._enabled = os.environ.get(env, "numba") != off_value

    def available(self) -> bool:
        """True when the kernels can run (importable and not switched off)."""
        return self.importable and self._enabled

    def set_enabled(self, enabled: bool) -> bool:
        """Switch the kernels on or off; returns the old state (callers restore it)."""
        old, self._enabled = self._enabled, bool(enabled)
        return old
