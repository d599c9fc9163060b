"""Shared fixtures: where ../shared/data lives (tests that need it skip when it is absent)."""

from __future__ import annotations

import hashlib
import os
import signal
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO.parent / "shared" / "data"


# Modules whose fixtures take minutes: collected first, so on the suite's 2 processes (pytest-xdist, whole modules
# per process in collection order, `addopts` in pyproject.toml) they start at once and the rest of the suite runs
# beside them (the small-SfM fixture is the suite's critical path).
SLOW_MODULES_FIRST = ("test_calibration_run.py",)

# One library thread per test process when the suite runs on several (pytest-xdist): two processes of two OpenMP
# threads each on 2 cores make every parallel region wait for a descheduled thread (a 1024-ray training step took
# 2.6-3.6 s instead of 0.24 s, docs/benchmarks.md). Set before torch is imported, in the environment too, so
# in-process runs and the subprocesses a test starts use the same thread count.
if os.environ.get("PYTEST_XDIST_WORKER"):
    for _var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
        os.environ[_var] = "1"
    if "torch" in sys.modules:
        sys.modules["torch"].set_num_threads(1)


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    items.sort(key=lambda item: item.path.name not in SLOW_MODULES_FIRST)  # stable: the rest keep their order


@pytest.fixture(scope="session")
def shared_data() -> Path:
    if not SHARED_DATA.is_dir():
        pytest.skip(f"{SHARED_DATA} is absent")
    return SHARED_DATA


@pytest.fixture(scope="session")
def tiny_capture(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A simulated `tiny` capture (seed 0), made once per test session. Treat it as read-only."""
    from lightstage.simulator.simulate import simulate_capture

    return simulate_capture(tmp_path_factory.mktemp("sim") / "tiny", preset="tiny", seed=0, progress=False)


class ProcessKiller:
    """SIGKILLs process `pid` from a background thread once `ready()` holds (or at the timeout): fault
    injection for runs on a real cluster. Use as a context manager around the run; `killed` says it happened."""

    def __init__(self, pid: int, ready: Callable[[], bool], timeout_s: float = 60.0) -> None:
        self.pid, self.ready, self.timeout_s = pid, ready, timeout_s
        self.killed = False
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        deadline = time.time() + self.timeout_s
        while time.time() < deadline and not self.ready():
            time.sleep(0.01)
        os.kill(self.pid, signal.SIGKILL)
        self.killed = True

    def __enter__(self) -> ProcessKiller:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._thread.join()


@pytest.fixture
def kill_process_when() -> type[ProcessKiller]:
    """`with kill_process_when(pid, ready): run(...)` kills `pid` mid-run (see ProcessKiller)."""
    return ProcessKiller


@pytest.fixture
def tree_hash() -> Callable[[Path], str]:
    """sha256 over every file's relative path and bytes under a directory (same bytes <=> same hash)."""

    def digest(root: Path) -> str:
        h = hashlib.sha256()
        for p in sorted(root.rglob("*")):
            if p.is_file():
                h.update(str(p.relative_to(root)).encode())
                h.update(p.read_bytes())
        return h.hexdigest()

    return digest
