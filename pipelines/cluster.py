"""How the pipeline executes its batch stages: the `cluster:` settings of a pipeline config and the one
executor a run builds from them (lightstage.executor: a dask LocalCluster of single-threaded worker
processes, an existing scheduler, batch jobs of workers on SLURM or PBS through dask-jobqueue, or an in-process
loop for `workers: 0`)."""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Any, Literal

from lightstage.config import require
from lightstage.dask_executor import dask_executor, jobqueue_cluster, jobqueue_executor
from lightstage.executor import Executor, LoopExecutor

# the keys that only a batch-queue cluster (kind slurm or pbs) reads
JOB_KEYS = (
    "jobs", "cores", "memory", "queue", "account", "walltime", "job_extra", "prologue", "python", "interface",
    "local_directory", "log_directory",
)  # fmt: skip


@dataclass(frozen=True)
class ClusterSettings:
    """How to get an executor. `kind: local`: an existing scheduler address (`scheduler`), or a LocalCluster of
    `workers` processes (0: no dask, everything in this process). `kind: slurm` / `pbs`: `jobs` batch jobs, each
    of `cores` cores and `memory` running cores / threads_per_worker single-threaded worker processes, submitted
    to `queue` (partition) under `account` for `walltime`; `job_extra`: more directives (e.g. "--exclusive");
    `prologue`: shell lines run first in each job (e.g. "source /path/venv/bin/activate"); `python`: the workers'
    interpreter (default this one's); `interface`: the network interface scheduler and workers talk on (e.g. ib0);
    `local_directory`: worker scratch; `log_directory`: where the jobs' output goes. The scheduler runs in the
    process that runs the pipeline (docs/cluster.md)."""

    kind: Literal["local", "slurm", "pbs"] = "local"
    scheduler: str | None = None
    workers: int = 2
    threads_per_worker: int = 1
    memory_limit: str = "auto"  # per worker: "auto" (machine memory / workers) or e.g. "4GiB"
    dashboard: str = ":0"  # LocalCluster dashboard address; ":0" picks a free port, "" = ":0" but not printed
    jobs: int = 1
    cores: int = 16
    memory: str = "64GB"
    queue: str | None = None
    account: str | None = None
    walltime: str = "04:00:00"
    job_extra: tuple[str, ...] = ()
    prologue: tuple[str, ...] = ()
    python: str | None = None
    interface: str | None = None
    local_directory: str | None = None
    log_directory: str | None = None

    def __post_init__(self) -> None:
        if self.kind == "local":
            defaults = {f.name: f.default for f in fields(self)}
            for key in JOB_KEYS:
                require(
                    getattr(self, key) == defaults[key], key, "only for kind slurm or pbs (kind is local)"
                )
        else:
            require(
                self.scheduler is None, "scheduler", f"kind {self.kind} starts its own scheduler; drop one"
            )
            require(self.jobs >= 1, "jobs", f"expected an integer >= 1, got {self.jobs}")
            require(self.cores >= 1, "cores", f"expected an integer >= 1, got {self.cores}")

    def job_options(self) -> dict[str, Any]:
        """dask-jobqueue's keywords for one batch job of workers."""
        return {
            "cores": self.cores,
            "memory": self.memory,
            "queue": self.queue,
            "account": self.account,
            "walltime": self.walltime,
            "job_extra_directives": list(self.job_extra),
            "job_script_prologue": list(self.prologue),
            "python": self.python,
            "interface": self.interface,
            "local_directory": self.local_directory,
            "log_directory": self.log_directory,
        }


def job_script(settings: ClusterSettings) -> str:
    """The batch script one job of workers runs (kind slurm or pbs), as dask-jobqueue writes it (no job is
    submitted); `lightstage config job-script CONFIG` prints it."""
    cluster = jobqueue_cluster(settings.kind, settings.threads_per_worker, **settings.job_options())
    try:
        return cluster.job_script()
    finally:
        cluster.close()


def open_executor(settings: ClusterSettings, verbose: bool = True) -> Executor:
    """The executor for `settings` (close it when done): dask when a scheduler, workers or a batch queue are
    given."""
    if settings.kind != "local":
        return jobqueue_executor(
            settings.kind, settings.jobs, settings.threads_per_worker, verbose, **settings.job_options()
        )
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
