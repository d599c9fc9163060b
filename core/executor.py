"""The one way stages run per-item work: an Executor maps a function over jobs in this process (a loop), in a
local process pool, or on a dask cluster (`lightstage.dask_executor`), with the same results in the same order.

Stages describe their work as small picklable jobs and importable top-level functions that return small
records, and receive an executor from their caller (the pipeline builds one per run); they never import
dask, which only `lightstage.dask_executor` imports, lazily. Every `map`:

- keeps at most `window` tasks in flight (default 4 per task slot), so 60k frames never flood a scheduler;
- returns results in item order and shows one tqdm progress bar (`desc`);
- retries a task that failed on an *environment* error (`lightstage.errors.is_environment_error`: disk full,
  permission denied, I/O error, a vanished temp file) up to `retries` times with a short backoff; a
  *content* error (bad input: any other exception) is never retried: with `errors="return"` the item gets a
  TaskFailure and the batch goes on, with `errors="raise"` the rest is cancelled and the error raised;
- survives a killed worker process: dask reschedules the task, the pool is rebuilt and its tasks resubmitted.

`map_groups` is the fan-in form: each group's parts run as tasks, then one task merges their results
(preprocess: the chunks of a view, then the view).
"""

from __future__ import annotations

import concurrent.futures as cf
import os
import time
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

from lightstage.errors import EnvironmentFault, LightstageError, is_environment_error

DEFAULT_RETRIES = 2  # environment errors only
RETRY_DELAY_S = 0.1  # first backoff; doubles with every attempt
MAX_WORKER_DEATHS = 3  # pool: a task in flight when its worker died this often fails (dask: allowed-failures)

# Environment of worker processes: BLAS/OpenMP pools sized to one thread before any library loads.
SINGLE_THREAD_ENV = {
    "OMP_NUM_THREADS": "1",
    "OPENBLAS_NUM_THREADS": "1",
    "MKL_NUM_THREADS": "1",
    "OPENCV_FOR_THREADS_NUM": "1",
}


@dataclass(frozen=True)
class TaskFailure:
    """What `map(..., errors="return")` gives for an item whose task failed (after retries, if any)."""

    item: Any
    error: str
    environment: bool = False  # an environment error that outlived its retries (not a content error)

    def __bool__(self) -> bool:  # lets callers write `if not result:` for failures
        return False


def describe(exc: BaseException) -> str:
    """One line for an exception: a LightstageError's own message (it names the file and the problem), else
    the type and the first line of the message."""
    text = str(exc).strip().splitlines()
    if isinstance(exc, LightstageError) and text:
        return text[0]
    return f"{type(exc).__name__}: {text[0]}" if text else type(exc).__name__


@dataclass
class _Unit:
    """One item (or group) of a map and how often it was tried."""

    index: int
    item: Any
    parts: Sequence[Any] = ()
    attempts: int = 0
    deaths: int = 0
    done: list[Any] = field(default_factory=list)
    left: int = 0


class Executor:
    """Base class: `map` and `map_groups` over a backend that submits calls and reports finished ones."""

    kind = "abstract"

    def slots(self) -> int:
        """How many tasks can run at once (at least 1)."""
        return 1

    def close(self) -> None:
        """Release processes or connections this executor owns."""

    def __enter__(self) -> Executor:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ---- the backend (overridden) ----
    def _session(self, fn: Callable[..., Any]) -> Any:
        raise NotImplementedError

    # ---- the public maps ----
    def map(
        self,
        fn: Callable[[Any], Any],
        items: Sequence[Any],
        *,
        desc: str | None = None,
        progress: bool = True,
        unit: str = "task",
        weight: Callable[[Any], int] | None = None,
        window: int | None = None,
        retries: int = DEFAULT_RETRIES,
        errors: str = "raise",
    ) -> list[Any]:
        """`[fn(item) for item in items]`, in parallel, in item order (see the module docstring)."""
        units = [_Unit(i, it) for i, it in enumerate(items)]
        return self._drive(fn, None, units, desc, progress, unit, weight, window, retries, errors)

    def map_groups(
        self,
        fn: Callable[[Any, list[Any]], Any],
        part_fn: Callable[[Any], Any],
        groups: Sequence[tuple[Any, Sequence[Any]]],
        *,
        desc: str | None = None,
        progress: bool = True,
        unit: str = "task",
        weight: Callable[[Any], int] | None = None,
        window: int | None = None,
        retries: int = DEFAULT_RETRIES,
        errors: str = "raise",
    ) -> list[Any]:
        """`[fn(item, [part_fn(p) for p in parts]) for item, parts in groups]`: the parts as tasks, then the
        merge as a task once they are done. A failed part fails its group (retried as a whole on an
        environment error). `window` counts tasks in flight; a group is admitted whole."""
        units = [_Unit(i, it, list(parts)) for i, (it, parts) in enumerate(groups)]
        return self._drive(fn, part_fn, units, desc, progress, unit, weight, window, retries, errors)

    # ---- the driver ----
    def _window(self, window: int | None) -> int:
        return max(1, window or 4 * self.slots())

    def _drive(
        self,
        fn: Callable[..., Any],
        part_fn: Callable[[Any], Any] | None,
        units: list[_Unit],
        desc: str | None,
        progress: bool,
        unit: str,
        weight: Callable[[Any], int] | None,
        window: int | None,
        retries: int,
        errors: str,
    ) -> list[Any]:
        if errors not in ("raise", "return"):
            raise ValueError("errors must be 'raise' or 'return'")
        from tqdm import tqdm

        size = weight or (lambda item: 1)
        results: list[Any] = [None] * len(units)
        limit = self._window(window)
        pending = deque(units)
        running: dict[Any, tuple[_Unit, int | None]] = {}
        session = self._session(fn)
        bar = tqdm(
            total=sum(size(u.item) for u in units),
            desc=desc,
            unit=unit,
            disable=not progress,
            dynamic_ncols=True,
        )

        def start(u: _Unit) -> None:
            if part_fn is None:
                running[session.submit(fn, u.item)] = (u, None)
            elif not u.parts:
                running[session.submit(fn, u.item, [])] = (u, None)
            else:
                u.done, u.left = [None] * len(u.parts), len(u.parts)
                for j, p in enumerate(u.parts):
                    running[session.submit(part_fn, p)] = (u, j)

        def drop(u: _Unit) -> None:
            for h, (other, _) in list(running.items()):
                if other is u:
                    session.cancel(h)
                    del running[h]

        def fail(u: _Unit, exc: BaseException) -> None:
            env = is_environment_error(exc)
            if env and u.attempts < retries:
                u.attempts += 1
                time.sleep(RETRY_DELAY_S * 2 ** (u.attempts - 1))
                pending.appendleft(u)
                return
            if errors == "raise":
                if env and not isinstance(exc, EnvironmentFault):
                    raise EnvironmentFault(
                        f"{desc or task_name(fn)}: {u.item!r} failed after {u.attempts + 1} attempt(s): {describe(exc)}"
                    ) from exc
                raise exc
            results[u.index] = TaskFailure(u.item, describe(exc), env)
            bar.update(size(u.item))

        try:
            while pending or running:
                while pending and len(running) < limit:
                    start(pending.popleft())
                for h in session.wait(list(running)):
                    if h not in running:
                        continue
                    u, j = running.pop(h)
                    ok, value = session.outcome(h)
                    if ok and j is None:
                        results[u.index] = value
                        bar.update(size(u.item))
                    elif ok:
                        u.done[j] = value
                        u.left -= 1
                        if u.left == 0:
                            running[session.submit(fn, u.item, u.done)] = (u, None)
                    elif session.broken(value):  # a pool worker died: every task in flight is lost
                        lost = {id(v[0]): v[0] for v in running.values()} | {id(u): u}
                        for h2 in list(running):
                            session.cancel(h2)
                        running.clear()
                        session.recover()
                        for v in sorted(lost.values(), key=lambda x: -x.index):
                            v.deaths += 1
                            if v.deaths >= MAX_WORKER_DEATHS:
                                fail(
                                    v, LightstageError(f"worker process died {v.deaths} times on {v.item!r}")
                                )
                            else:
                                pending.appendleft(v)
                        break
                    else:
                        drop(u)
                        fail(u, value)
            return results
        except BaseException:
            for h in list(running):
                session.cancel(h)
            raise
        finally:
            bar.close()
            session.close()


def task_name(fn: Callable[..., Any]) -> str:
    """A function's name for progress bars, messages and task keys."""
    return getattr(fn, "__name__", "task")


# ---- in-process loop ----------------------------------------------------------------------------------------
class _LoopSession:
    """Runs each call at submission; its 'future' is already done."""

    def submit(self, fn: Callable[..., Any], *args: Any) -> cf.Future:
        fut: cf.Future = cf.Future()
        try:
            fut.set_result(fn(*args))
        except Exception as e:  # noqa: BLE001 - the driver decides: retry, record or raise
            fut.set_exception(e)
        return fut

    def wait(self, handles: list[cf.Future]) -> list[cf.Future]:
        return handles

    def outcome(self, h: cf.Future) -> tuple[bool, Any]:
        exc = h.exception()
        return (False, exc) if exc is not None else (True, h.result())

    def cancel(self, h: cf.Future) -> None:
        pass

    def broken(self, exc: BaseException) -> bool:
        return False

    def recover(self) -> None:
        pass

    def close(self) -> None:
        pass


class LoopExecutor(Executor):
    """Everything in this process, one task at a time (debugging, tests, `--workers 0`)."""

    kind = "loop"

    def _window(self, window: int | None) -> int:
        return 1

    def _session(self, fn: Callable[..., Any]) -> _LoopSession:
        return _LoopSession()


# ---- local process pool ---------------------------------------------------------------------------------------
def _pool_worker_init(threads: int) -> None:
    """Start-up of each pool worker: one thread per native library (the work scales with processes)."""
    os.environ.update({k: str(threads) for k in SINGLE_THREAD_ENV})
    from lightstage.threads import set_library_threads

    set_library_threads(threads)


class _PoolSession(_LoopSession):
    def __init__(self, owner: PoolExecutor) -> None:
        self.owner = owner

    def submit(self, fn: Callable[..., Any], *args: Any) -> cf.Future:
        return self.owner.pool().submit(fn, *args)

    def wait(self, handles: list[cf.Future]) -> list[cf.Future]:
        done, _ = cf.wait(handles, return_when=cf.FIRST_COMPLETED)
        return sorted(done, key=handles.index)

    def cancel(self, h: cf.Future) -> None:
        h.cancel()

    def broken(self, exc: BaseException) -> bool:
        from concurrent.futures.process import BrokenProcessPool

        return isinstance(exc, BrokenProcessPool)

    def recover(self) -> None:
        self.owner.close()


class PoolExecutor(Executor):
    """A local pool of `workers` spawned processes (spawn, not fork: forking a process that already runs
    threads can deadlock the child), created on first use and rebuilt when a worker dies."""

    kind = "pool"

    def __init__(self, workers: int, threads_per_worker: int = 1) -> None:
        if workers < 1:
            raise LightstageError(f"workers: expected at least 1 process, got {workers}")
        self.workers = workers
        self.threads = threads_per_worker
        self._pool: cf.ProcessPoolExecutor | None = None

    def slots(self) -> int:
        return self.workers

    def pool(self) -> cf.ProcessPoolExecutor:
        if self._pool is None:
            import multiprocessing

            self._pool = cf.ProcessPoolExecutor(
                self.workers,
                mp_context=multiprocessing.get_context("spawn"),
                initializer=_pool_worker_init,
                initargs=(self.threads,),
            )
        return self._pool

    def _session(self, fn: Callable[..., Any]) -> _PoolSession:
        return _PoolSession(self)

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool = None


def local_executor(workers: int | None) -> Executor:
    """A loop for 0/1/None workers, else a process pool of `workers` (standalone stage commands)."""
    return PoolExecutor(workers) if workers and workers > 1 else LoopExecutor()
