"""The executor interface: a loop, a process pool and a dask LocalCluster give the same ordered results;
environment errors are retried and then succeed, content errors are not retried; a killed pool worker's tasks
are resubmitted."""

from __future__ import annotations

import errno
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from lightstage.dask_executor import WORKER_MALLOC_ENV, dask_executor
from lightstage.errors import EnvironmentFault, LightstageError, is_environment_error
from lightstage.executor import LoopExecutor, PoolExecutor, TaskFailure


# ---- tasks (top level: the pool and dask workers import them from this module) ---------------------------
def square(x: int) -> int:
    time.sleep(0.002 * (x % 3))  # finish out of order
    return x * x


def content_error_on_3(x: int) -> int:
    if x == 3:
        raise LightstageError(f"frame {x}: corrupt")
    return x


def flaky(item: tuple[str, int, int]) -> int:
    """Fails with an environment error until it has been called `fails` times (counted in a folder)."""
    folder, x, fails = item
    marker = Path(folder) / f"{x}.{len(list(Path(folder).glob(f'{x}.*')))}"
    marker.touch()
    if len(list(Path(folder).glob(f"{x}.*"))) <= fails:
        raise OSError(errno.ENOSPC, "No space left on device", str(marker))
    return x


def counted_content_error(item: tuple[str, int]) -> int:
    folder, x = item
    (Path(folder) / f"{x}.{time.monotonic_ns()}").touch()
    raise ValueError(f"bad pixels in {x}")


def chunk_sum(part: list[int]) -> int:
    return sum(part)


def merge(label: str, parts: list[int]) -> str:
    return f"{label}={sum(parts)}"


def kill_once(item: tuple[str, int]) -> int:
    """The first task with x == 2 kills its own worker process (kill -9); the retry succeeds."""
    folder, x = item
    flag = Path(folder) / "killed"
    if x == 2 and not flag.exists():
        flag.touch()
        os.kill(os.getpid(), signal.SIGKILL)
    return x + 100


@pytest.fixture(scope="module")
def dask() -> object:
    ex = dask_executor(workers=2, dashboard="", verbose=False)
    yield ex
    ex.close()


def test_workers_get_the_malloc_settings_and_this_process_keeps_its_own(monkeypatch) -> None:
    for k in WORKER_MALLOC_ENV:
        monkeypatch.delenv(k, raising=False)
    ex = dask_executor(workers=1, dashboard="", verbose=False)
    try:
        seen = ex.client.run(lambda: {k: os.environ.get(k) for k in WORKER_MALLOC_ENV})
    finally:
        ex.close()
    assert list(seen.values()) == [WORKER_MALLOC_ENV]
    # dask's nanny sets them here before spawning: they must not leak into what this process starts later
    assert not any(k in os.environ for k in WORKER_MALLOC_ENV)


_FREED_BLOCK_RSS = """
import json, numpy as np
from lightstage.malloc import release_free_heap
def rss_mb():
    return int(open("/proc/self/statm").read().split()[1]) * 4096 / 2**20
block = np.ones(300 * 2**20, np.uint8)  # a whole raw frame's size, touched
del block
kept = rss_mb()
print(json.dumps([kept, release_free_heap(), rss_mb()]))
"""


@pytest.mark.skipif(not Path("/proc/self/statm").exists(), reason="needs Linux /proc for resident memory")
def test_release_free_heap_gives_back_what_the_worker_settings_keep() -> None:
    """Under the workers' thresholds a freed 300 MB block stays resident until `release_free_heap` (glibc)."""
    env = {**os.environ, **WORKER_MALLOC_ENV}
    out = subprocess.run([sys.executable, "-c", _FREED_BLOCK_RSS], env=env, capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    kept, released, after = json.loads(out.stdout)
    if not released:
        pytest.skip("no glibc malloc_trim here")
    assert kept - after > 250, (kept, after)


def executors(dask_ex) -> list:
    return [LoopExecutor(), PoolExecutor(2), dask_ex]


def test_same_ordered_results_everywhere(dask) -> None:
    items = list(range(23))
    groups = [(f"v{i}", [[i, 1], [i, 2, 3]]) for i in range(5)]
    for ex in executors(dask):
        with ex if ex is not dask else _nothing():
            assert ex.map(square, items, progress=False, window=3) == [x * x for x in items], ex.kind
            got = ex.map_groups(merge, chunk_sum, groups, progress=False, window=2)
            assert got == [f"v{i}={2 * i + 6}" for i in range(5)], ex.kind


def test_environment_error_is_retried_then_succeeds(tmp_path: Path, dask) -> None:
    for ex in executors(dask):
        folder = tmp_path / ex.kind
        folder.mkdir()
        items = [(str(folder), x, 2 if x == 1 else 0) for x in range(4)]  # item 1 fails twice, then works
        with ex if ex is not dask else _nothing():
            assert ex.map(flaky, items, progress=False, retries=2) == [0, 1, 2, 3], ex.kind
        assert len(list(folder.glob("1.*"))) == 3, ex.kind
        # more failures than retries: one clear error (an EnvironmentFault, one line for the CLI)
        more = tmp_path / f"{ex.kind}-more"
        more.mkdir()
        with ex if ex is not dask else _nothing():
            with pytest.raises(EnvironmentFault, match="No space left"):
                ex.map(flaky, [(str(more), 0, 5)], progress=False, retries=1)
            out = ex.map(flaky, [(str(more), 7, 5)], progress=False, retries=1, errors="return")
        assert isinstance(out[0], TaskFailure) and out[0].environment, ex.kind


def test_content_error_is_not_retried(tmp_path: Path, dask) -> None:
    for ex in executors(dask):
        folder = tmp_path / ex.kind
        folder.mkdir()
        with ex if ex is not dask else _nothing():
            out = ex.map(content_error_on_3, list(range(6)), progress=False, errors="return")
            assert out[:3] == [0, 1, 2] and out[4:] == [4, 5], ex.kind
            assert isinstance(out[3], TaskFailure) and "frame 3: corrupt" in out[3].error
            assert not out[3].environment
            with pytest.raises(LightstageError, match="frame 3: corrupt"):
                ex.map(content_error_on_3, list(range(6)), progress=False)
            with pytest.raises(ValueError, match="bad pixels"):
                ex.map(counted_content_error, [(str(folder), 1)], progress=False, retries=3)
        assert len(list(folder.glob("1.*"))) == 1, ex.kind  # tried once


def test_environment_errors_are_told_apart() -> None:
    assert is_environment_error(OSError(errno.ENOSPC, "full"))
    assert is_environment_error(PermissionError(errno.EACCES, "denied"))
    assert is_environment_error(EnvironmentFault("disk hiccup"))
    assert is_environment_error(FileNotFoundError(errno.ENOENT, "gone", "/w/.frame.ab12.tmp.exr"))
    assert not is_environment_error(FileNotFoundError(errno.ENOENT, "missing", "/capture/000.exr"))
    assert not is_environment_error(LightstageError("corrupt"))
    assert not is_environment_error(ValueError("bad"))


def test_pool_worker_killed_is_resubmitted(tmp_path: Path) -> None:
    with PoolExecutor(2) as ex:
        items = [(str(tmp_path), x) for x in range(6)]
        assert ex.map(kill_once, items, progress=False) == [x + 100 for x in range(6)]
    assert (tmp_path / "killed").exists()


class _nothing:
    def __enter__(self) -> None:
        return None

    def __exit__(self, *exc: object) -> None:
        return None
