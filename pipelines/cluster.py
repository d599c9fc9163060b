"""How the pipeline executes its batch stages: the `cluster:` settings of a pipeline config and the one
executor a run builds from them (lightstage.executor: a dask LocalCluster of single-threaded worker
processes, an existing scheduler, or an in-process loop for `workers: 0`)."""

from __future__ import annotations

from dataclasses import dataclass

from lightstage.dask_executor import dask_executor
from lightstage.executor import Executor, LoopExecutor


@dataclass(frozen=True)
class ClusterSettings:
    """How to get an executor: an existing scheduler address, or a LocalCluster of `workers` processes
    (0: no dask, everything in this process)."""

    scheduler: str | None = None
    workers: int = 2
    threads_per_worker: int = 1
    memory_limit: str = "auto"  # per worker: "auto" (machine memory / workers) or e.g. "4GiB"
    dashboard: str = ":0"  # LocalCluster dashboard address; ":0" picks a free port, "" = ":0" but not printed


def open_executor(settings: ClusterSettings, verbose: bool = True) -> Executor:
    """The executor for `settings` (close it when done): dask when a scheduler or workers are given."""
    if not settings.scheduler and settings.workers == 0:
        return LoopExecutor()
    return dask_executor(
        settings.scheduler,
        settings.workers,
        settings.threads_per_worker,
        settings.memory_limit,
        settings.dashboard,
        verbose,
    )
