"""The dask backend of `lightstage.executor`: a DaskExecutor over a distributed.Client, started on a LocalCluster
of single-threaded worker processes or connected to a running scheduler. Imported only where a stage runs on
dask (dask itself is imported lazily inside), so stages never see it."""

from __future__ import annotations

import contextlib
import itertools
import logging
import os
import sys
import uuid
from collections.abc import Callable
from typing import Any

from lightstage.errors import EnvironmentFault, LightstageError
from lightstage.executor import SINGLE_THREAD_ENV, Executor, task_name
from lightstage.malloc import WORKER_MALLOC_ENV


def _lost_scheduler(client: Any, detail: str) -> LightstageError:
    """The error of a run whose scheduler went away (killed, its node lost): finished outputs are kept, so the
    same command resumes once a scheduler (and workers) run again."""
    where = getattr(getattr(client, "scheduler", None), "address", None) or "the dask scheduler"
    return LightstageError(
        f"lost the connection to dask scheduler {where} ({detail}); finished outputs are kept: "
        "start the scheduler and workers again and rerun the same command to resume"
    )


class _DaskSession:
    def __init__(self, client: Any, fn: Callable[..., Any]) -> None:
        from distributed import as_completed

        self.client = client
        self.prefix = f"{task_name(fn)}-{uuid.uuid4().hex[:10]}"
        self.counter = itertools.count()
        self.queue = as_completed()

    def _gone(self, exc: BaseException) -> bool:
        """Whether `exc` means the scheduler connection is gone (not a task's own error)."""
        from distributed.client import ClosedClientError
        from distributed.comm.core import CommClosedError

        return isinstance(exc, CommClosedError | ClosedClientError) or self.client.status in (
            "closed",
            "closing",
        )

    def submit(self, fn: Callable[..., Any], *args: Any) -> Any:
        key = f"{self.prefix}-{next(self.counter)}"
        try:
            fut = self.client.submit(fn, *args, key=key, pure=False)
        except Exception as e:
            if self._gone(e):
                raise _lost_scheduler(self.client, f"{type(e).__name__}: {e}") from None
            raise
        self.queue.add(fut)
        return fut

    def wait(self, handles: list[Any]) -> list[Any]:
        return [next(self.queue)]

    def outcome(self, h: Any) -> tuple[bool, Any]:
        try:
            if h.status == "finished":
                try:
                    return True, h.result()
                except Exception as e:
                    if self._gone(e):
                        raise _lost_scheduler(self.client, f"{type(e).__name__}: {e}") from None
                    raise
            if self._gone(RuntimeError()):
                raise _lost_scheduler(self.client, f"task {h.key} {h.status} when the client closed")
            if h.status == "cancelled":
                return False, EnvironmentFault(f"task {h.key} was cancelled by the scheduler")
            try:
                return False, h.exception()
            except Exception as e:  # noqa: BLE001 - a lost future raises here
                return False, e
        finally:
            try:
                h.release()
            except Exception:  # noqa: BLE001 - a closed client has nothing left to release
                pass

    def cancel(self, h: Any) -> None:
        try:
            h.cancel()
        except Exception as e:  # noqa: BLE001 - cleanup after the scheduler went away: nothing to cancel there
            if not self._gone(e):
                raise

    def broken(self, exc: BaseException) -> bool:
        return False

    def recover(self) -> None:
        pass

    def close(self) -> None:
        self.queue.clear()


class DaskExecutor(Executor):
    """Tasks on a dask cluster through `client` (a distributed.Client); a killed worker's tasks are
    rescheduled by dask on the others. `owned` exit stack: what `close` shuts down (cluster, client)."""

    kind = "dask"

    def __init__(self, client: Any, owned: contextlib.ExitStack | None = None) -> None:
        self.client = client
        self._owned = owned

    def slots(self) -> int:
        try:
            return max(1, sum(self.client.nthreads().values()))
        except Exception:  # noqa: BLE001 - a scheduler hiccup must not stop a stage from sizing its window
            return 1

    def _session(self, fn: Callable[..., Any]) -> _DaskSession:
        return _DaskSession(self.client, fn)

    def worker_pids(self) -> list[int]:
        """The process ids of the cluster's workers (tests and benchmarks kill one)."""
        return sorted(self.client.run(os.getpid).values())

    def close(self) -> None:
        if self._owned is not None:
            self._owned.close()
            self._owned = None


def library_threads_plugin(n: int) -> Any:
    """A dask WorkerPlugin giving every worker (restarted ones too) `n` threads per native library."""
    from distributed.diagnostics.plugin import WorkerPlugin

    class LibraryThreadsPlugin(WorkerPlugin):
        name = "lightstage-library-threads"
        idempotent = True

        def setup(self, worker: Any) -> None:
            from lightstage.threads import set_library_threads

            set_library_threads(n)

    return LibraryThreadsPlugin()


def worker_spawn_environ() -> dict[str, Any]:
    """dask's `distributed.nanny.pre-spawn-environ` with lightstage's worker malloc settings added."""
    import dask

    return {**dask.config.get("distributed.nanny.pre-spawn-environ", {}), **WORKER_MALLOC_ENV}


def in_dask_worker() -> bool:
    """Whether this code runs inside a dask worker (tasks there set one library thread per process)."""
    try:
        from distributed import get_worker

        get_worker()
        return True
    except (ImportError, ValueError):
        return False


def dask_executor(
    scheduler: str | None = None,
    workers: int = 2,
    threads_per_worker: int = 1,
    memory_limit: str = "auto",
    dashboard: str = ":0",
    verbose: bool = True,
) -> DaskExecutor:
    """Connect to `scheduler` (tcp://HOST:PORT) or start a LocalCluster of `workers` single-threaded worker
    processes; every worker gets one library thread per worker thread. Close the executor to stop it."""
    from distributed import Client, LocalCluster

    stack = contextlib.ExitStack()
    if scheduler:
        try:
            client = Client(scheduler, timeout="20s")
        except (OSError, TimeoutError) as e:
            raise LightstageError(f"cannot connect to dask scheduler {scheduler}: {e}") from None
        stack.callback(client.close)
    else:
        if workers < 1:
            raise LightstageError(f"cluster.workers: expected at least 1 worker, got {workers}")
        import dask

        env = {k: str(threads_per_worker) for k in SINGLE_THREAD_ENV}
        spawn_env = worker_spawn_environ()
        # dask's nanny writes the pre-spawn variables into this process's environment before it spawns a
        # worker; put it back, so processes this one starts later (training, pools) keep glibc's defaults
        saved = {k: os.environ.get(k) for k in spawn_env}
        try:
            with dask.config.set({"distributed.nanny.pre-spawn-environ": spawn_env}):
                cluster = LocalCluster(
                    n_workers=workers,
                    threads_per_worker=threads_per_worker,
                    processes=True,
                    memory_limit=memory_limit,
                    dashboard_address=dashboard or ":0",  # the HTTP server starts anyway: never a fixed port
                    silence_logs=logging.ERROR,
                    env=env,
                )
        finally:
            for k, v in saved.items():
                if v is None:
                    os.environ.pop(k, None)
                else:
                    os.environ[k] = v
        stack.callback(cluster.close)
        client = Client(cluster)
        stack.callback(client.close)
    try:
        client.register_plugin(library_threads_plugin(threads_per_worker))
    except BaseException:
        stack.close()
        raise
    if verbose:
        where = scheduler or f"LocalCluster, {workers} worker processes"
        link = getattr(client, "dashboard_link", None) if (scheduler or dashboard) else None
        print(f"dask: {where}" + (f"; dashboard {link}" if link else ""), file=sys.stderr)
    return DaskExecutor(client, stack)


JOBQUEUE_KINDS = ("slurm", "pbs")


def jobqueue_cluster(kind: str, threads_per_worker: int = 1, **job: Any) -> Any:
    """A dask-jobqueue cluster (SLURMCluster or PBSCluster) whose batch jobs each run `job["cores"] //
    threads_per_worker` worker processes with the same per-process library threads and malloc settings as a local
    worker (exported by the job script). `job`: dask-jobqueue's keywords (cores, memory, queue, account,
    walltime, job_extra_directives, job_script_prologue, python, interface, local_directory, log_directory).
    The scheduler runs in this process; no job is submitted until the cluster is scaled."""
    try:
        import dask_jobqueue
    except ImportError:
        raise LightstageError(
            f"cluster.kind {kind}: dask-jobqueue is not installed (pip install dask-jobqueue)"
        ) from None
    if kind not in JOBQUEUE_KINDS:
        raise LightstageError(f"cluster.kind: one of local, {', '.join(JOBQUEUE_KINDS)}; got {kind!r}")
    env = {**{k: str(threads_per_worker) for k in SINGLE_THREAD_ENV}, **WORKER_MALLOC_ENV}
    prologue = [f"export {k}={v}" for k, v in env.items()] + list(job.pop("job_script_prologue", ()))
    cores = int(job["cores"])
    if cores < threads_per_worker:
        raise LightstageError(f"cluster.cores: {cores} is fewer than threads_per_worker {threads_per_worker}")
    cls = {"slurm": dask_jobqueue.SLURMCluster, "pbs": dask_jobqueue.PBSCluster}[kind]
    options = {"dashboard_address": ":0"}
    if job.get("interface"):
        options["interface"] = job["interface"]
    return cls(
        processes=cores // threads_per_worker,
        job_script_prologue=prologue,
        scheduler_options=options,
        **{k: v for k, v in job.items() if v is not None},
    )


def jobqueue_executor(
    kind: str, jobs: int, threads_per_worker: int = 1, verbose: bool = True, **job: Any
) -> DaskExecutor:
    """A DaskExecutor on a SLURM or PBS cluster: `jobs` batch jobs of workers (jobqueue_cluster), submitted now;
    tasks queue on the scheduler until the jobs start. Closing the executor cancels the jobs."""
    from distributed import Client

    stack = contextlib.ExitStack()
    cluster = jobqueue_cluster(kind, threads_per_worker, **job)
    stack.callback(cluster.close)
    try:
        client = Client(cluster)
        stack.callback(client.close)
        client.register_plugin(library_threads_plugin(threads_per_worker))
        cluster.scale(jobs=jobs)
    except BaseException:
        stack.close()
        raise
    if verbose:
        link = getattr(client, "dashboard_link", None)
        print(
            f"dask: {kind} cluster, {jobs} jobs of {job['cores']} cores submitted"
            + (f"; dashboard {link}" if link else ""),
            file=sys.stderr,
        )
    return DaskExecutor(client, stack)
