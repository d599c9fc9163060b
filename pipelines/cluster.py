"""Dask execution for the batch stages: a LocalCluster of single-threaded worker processes (or an existing
cluster), and `map_bounded`, the one helper stages use to run per-item work as tasks in bounded windows.

Stages call `map_bounded(client, fn, items)`; with `client=None` it runs in-process, so the same stage code
serves the CLI, tests and the cluster. Tasks must be importable top-level functions returning small records.
"""

from __future__ import annotations

import contextlib
import logging
import os
import sys
import time
import uuid
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from typing import Any

from distributed.diagnostics.plugin import WorkerPlugin

from lightstage.errors import LightstageError

# Environment for worker processes: BLAS/OpenMP pools sized to one thread before any library loads.
_SINGLE_THREAD_ENV = {
    "OMP_NUM_THREADS": "1",
    "OPENBLAS_NUM_THREADS": "1",
    "MKL_NUM_THREADS": "1",
    "OPENCV_FOR_THREADS_NUM": "1",
}

# glibc malloc settings for worker processes, which must be in the environment before the process starts
# (dask's `pre-spawn-environ`). Dask sets MALLOC_TRIM_THRESHOLD_=64 KiB, which (1) freezes glibc's mmap
# threshold at 128 KiB, so every multi-MB band buffer of the per-frame work became a fresh mmap, and (2) hands
# the heap back to the OS after every free, so the next buffer page-faults again: each cost preprocess ~20% more
# CPU per raw frame (docs/benchmarks.md). Blocks up to 32 MiB come from the heap and up to 64 MiB of free heap
# is kept per worker (dask still sees it as unmanaged memory, well inside the worker's budget).
_WORKER_MALLOC_ENV = {"MALLOC_MMAP_THRESHOLD_": str(32 << 20), "MALLOC_TRIM_THRESHOLD_": str(64 << 20)}


def worker_spawn_environ() -> dict[str, Any]:
    """dask's `distributed.nanny.pre-spawn-environ` with lightstage's worker malloc settings added."""
    import dask

    return {**dask.config.get("distributed.nanny.pre-spawn-environ", {}), **_WORKER_MALLOC_ENV}


@dataclass(frozen=True)
class TaskFailure:
    """What `map_bounded(..., errors="return")` gives for an item whose task failed after its retries."""

    item: Any
    error: str

    def __bool__(self) -> bool:  # lets callers write `if not result:` for failures
        return False


class LibraryThreadsPlugin(WorkerPlugin):
    """Sets `n` threads for every native library in each worker process, restarted workers included."""

    name = "lightstage-library-threads"
    idempotent = True

    def __init__(self, n: int = 1) -> None:
        self.n = n

    def setup(self, worker: Any) -> None:
        from lightstage.threads import set_library_threads

        set_library_threads(self.n)


@dataclass(frozen=True)
class ClusterSettings:
    """How to get a dask client: an existing scheduler address, or a LocalCluster of `workers` processes."""

    scheduler: str | None = None
    workers: int = 2
    threads_per_worker: int = 1
    memory_limit: str = "auto"  # per worker: "auto" (machine memory / workers) or e.g. "4GiB"
    dashboard: str = ":0"  # LocalCluster dashboard address; ":0" picks a free port, "" = ":0" but not printed


@contextlib.contextmanager
def dask_client(settings: ClusterSettings, verbose: bool = True) -> Iterator[Any]:
    """Yield a distributed.Client for `settings`: connect to `scheduler` or start (and later stop) a
    LocalCluster. Every worker gets one library thread per worker thread; the dashboard address is printed."""
    from distributed import Client, LocalCluster

    cluster = None
    if settings.scheduler:
        try:
            client = Client(settings.scheduler, timeout="20s")
        except (OSError, TimeoutError) as e:
            raise LightstageError(f"cannot connect to dask scheduler {settings.scheduler}: {e}") from None
    else:
        if settings.workers < 1:
            raise LightstageError(f"cluster.workers: expected at least 1 worker, got {settings.workers}")
        env = dict(_SINGLE_THREAD_ENV)
        if settings.threads_per_worker != 1:
            env = {k: str(settings.threads_per_worker) for k in env}
        import dask

        with dask.config.set({"distributed.nanny.pre-spawn-environ": worker_spawn_environ()}):
            cluster = LocalCluster(
                n_workers=settings.workers,
                threads_per_worker=settings.threads_per_worker,
                processes=True,
                memory_limit=settings.memory_limit,
                dashboard_address=settings.dashboard
                or ":0",  # the HTTP server starts anyway: never on a fixed port
                silence_logs=logging.ERROR,
                env=env,
            )
        client = Client(cluster)
    try:
        client.register_plugin(LibraryThreadsPlugin(settings.threads_per_worker))
        if verbose:
            where = settings.scheduler or f"LocalCluster, {settings.workers} worker processes"
            link = (
                getattr(client, "dashboard_link", None)
                if (settings.scheduler or settings.dashboard)
                else None
            )
            print(f"dask: {where}" + (f"; dashboard {link}" if link else ""), file=sys.stderr)
        yield client
    finally:
        client.close()
        if cluster is not None:
            cluster.close()


def total_threads(client: Any) -> int:
    """How many task slots the cluster has now (at least 1)."""
    try:
        return max(1, sum(client.nthreads().values()))
    except Exception:  # noqa: BLE001 - a scheduler hiccup must not stop a stage from sizing its window
        return 1


def _progress_bar(total: int, desc: str | None, enabled: bool) -> Any:
    from tqdm import tqdm

    return tqdm(total=total, desc=desc, unit="task", disable=not enabled, leave=True, dynamic_ncols=True)


def _describe(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()
    return f"{type(exc).__name__}: {text[0]}" if text else type(exc).__name__


def map_bounded(
    client: Any,
    fn: Callable[[Any], Any],
    items: Iterable[Any],
    *,
    window: int | None = None,
    retries: int = 2,
    progress: bool = True,
    desc: str | None = None,
    errors: str = "raise",
) -> list[Any]:
    """Run `fn(item)` for every item and return the results in item order.

    With a dask `client`, at most `window` tasks (default 4 per worker thread) are in flight at once, so 60k
    items never flood the scheduler; a failed task is retried `retries` times (transient failures) and a task
    whose worker died is rescheduled by dask. `errors="return"` puts a TaskFailure in place of an item that
    still fails (the batch goes on); `errors="raise"` cancels the rest and raises. `client=None` runs the
    same loop in this process. `fn` must be an importable function and should return a small record.
    """
    if errors not in ("raise", "return"):
        raise ValueError("errors must be 'raise' or 'return'")
    items = list(items)
    results: list[Any] = [None] * len(items)
    bar = _progress_bar(len(items), desc, progress)
    try:
        if client is None:
            for i, item in enumerate(items):
                results[i] = _call_with_retries(fn, item, retries, errors)
                bar.update(1)
            return results
        _map_on_client(client, fn, items, results, window, retries, errors, bar)
        return results
    finally:
        bar.close()


def _call_with_retries(fn: Callable[[Any], Any], item: Any, retries: int, errors: str) -> Any:
    for attempt in range(retries + 1):
        try:
            return fn(item)
        except LightstageError as e:  # bad input is not transient: no retry
            if errors == "raise":
                raise
            return TaskFailure(item, _describe(e))
        except Exception as e:  # noqa: BLE001 - retried, then reported per item
            if attempt < retries:
                time.sleep(0.05 * (attempt + 1))
                continue
            if errors == "raise":
                raise
            return TaskFailure(item, _describe(e))
    raise AssertionError("unreachable")


def _map_on_client(
    client: Any,
    fn: Callable[[Any], Any],
    items: list[Any],
    results: list[Any],
    window: int | None,
    retries: int,
    errors: str,
    bar: Any,
) -> None:
    from distributed import as_completed

    window = max(1, window or 4 * total_threads(client))
    prefix = f"{getattr(fn, '__name__', 'task')}-{uuid.uuid4().hex[:10]}"
    index: dict[Any, int] = {}
    pending = iter(range(len(items)))
    queue = as_completed()

    def submit_next() -> bool:
        i = next(pending, None)
        if i is None:
            return False
        fut = client.submit(fn, items[i], key=f"{prefix}-{i}", retries=retries, pure=False)
        index[fut.key] = i
        queue.add(fut)
        return True

    for _ in range(min(window, len(items))):
        submit_next()
    try:
        for fut in queue:
            i = index.pop(fut.key)
            if fut.status == "error" or fut.status == "cancelled":
                try:
                    exc = fut.exception()
                except Exception as e:  # noqa: BLE001 - a cancelled future raises here
                    exc = e
                if errors == "raise":
                    if isinstance(exc, LightstageError):
                        raise exc
                    raise LightstageError(
                        f"task {prefix}-{i} ({items[i]!r}) failed: {_describe(exc)}"
                    ) from exc
                results[i] = TaskFailure(items[i], _describe(exc))
            else:
                results[i] = fut.result()
            fut.release()
            bar.update(1)
            submit_next()
    except BaseException:
        for fut in list(queue.futures):
            fut.cancel()
        raise


def worker_pid() -> int:
    """The process id of the caller (used by tests and benchmarks to find and kill a worker)."""
    return os.getpid()
