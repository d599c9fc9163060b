"""The scale bench scaled down: a paper-geometry capture (`paper-512`: 20 cameras, 9 groups' rig, 331-light
sphere; here 3 groups and 2 lights, 120 frames) through `lightstage run --to preprocess` on a cluster of
separate `dask scheduler` / `dask worker` processes. The scheduler is SIGKILLed mid-preprocess: the run exits
non-zero with one error line; a fresh scheduler and workers, and the same command again, finish with outputs
identical to an uninterrupted local run (bench/tree_hash.py)."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "bench"))

from tree_hash import tree_hash  # noqa: E402


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class DaskProcesses:
    """A `dask scheduler` and `dask worker` processes on loopback, as on real machines (no LocalCluster)."""

    def __init__(self, logs: Path, env: dict[str, str], workers: int = 2) -> None:
        self.logs, self.env, self.n = logs, env, workers
        self.procs: list[subprocess.Popen] = []
        self.address = ""
        self.scheduler: subprocess.Popen | None = None

    def _start(self, name: str, cmd: list[str]) -> subprocess.Popen:
        out = open(self.logs / f"{name}.log", "a")  # noqa: SIM115 - closed with the process
        p = subprocess.Popen(
            [sys.executable, "-m", *cmd],
            env=self.env,
            stdout=out,
            stderr=subprocess.STDOUT,
            start_new_session=True,
        )
        self.procs.append(p)
        return p

    def start(self) -> str:
        from distributed import Client

        port = _free_port()
        self.address = f"tcp://127.0.0.1:{port}"
        self.scheduler = self._start(
            "scheduler",
            ["distributed.cli.dask_scheduler", "--host", "127.0.0.1", "--port", str(port), "--no-dashboard"],
        )
        for i in range(self.n):
            self._start(
                f"worker{i}",
                ["distributed.cli.dask_worker", self.address, "--nthreads", "1", "--no-nanny", "--host",
                 "127.0.0.1", "--no-dashboard", "--memory-limit", "2GiB"],
            )  # fmt: skip
        with Client(self.address, timeout="30s") as client:
            client.wait_for_workers(self.n, timeout=60)
        return self.address

    def stop(self) -> None:
        for p in reversed(self.procs):
            if p.poll() is None:
                p.terminate()
        for p in self.procs:
            try:
                p.wait(timeout=20)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()
        self.procs = []


def _run(*args: str, env: dict[str, str]) -> subprocess.CompletedProcess:
    cmd = [sys.executable, "-m", "lightstage.pipelines.cli", "run", *args, "--to", "preprocess", "--quiet"]
    return subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=300)


@pytest.mark.slow
def test_scheduler_killed_mid_preprocess_then_resumed_matches_a_local_run(tmp_path: Path, kill_process_when):
    from lightstage.simulator.simulate import simulate_capture

    capture = simulate_capture(
        tmp_path / "paper512", preset="paper-512", seed=0, groups="0-2", lights="42,297", probe=False,
        progress=False, workers=2,
    )  # fmt: skip
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONUNBUFFERED": "1"}
    local = tmp_path / "local"
    proc = _run(str(capture), "--work", str(local), "--workers", "0", env=env)
    assert proc.returncode == 0, proc.stderr

    logs = tmp_path / "logs"
    logs.mkdir()
    work = tmp_path / "cluster"
    frames = work / "preprocess" / "frames"
    seen: list[int] = []

    def mid_preprocess() -> bool:
        n = sum(1 for _ in frames.rglob("*.exr")) if frames.is_dir() else 0
        seen.append(n)
        return n >= 30

    cluster = DaskProcesses(logs, env)
    try:
        address = cluster.start()
        with kill_process_when(cluster.scheduler.pid, mid_preprocess, timeout_s=120) as killer:
            proc = _run(str(capture), "--work", str(work), "--scheduler", address, env=env)
        assert killer.killed and proc.returncode != 0
        errors = [ln for ln in proc.stderr.splitlines() if ln.startswith("lightstage: error:")]
        # one error line, the last; no uncaught exception (dask's client may log its reconnect attempts first)
        assert len(errors) == 1 and proc.stderr.strip().splitlines()[-1] == errors[0], proc.stderr[-3000:]
        assert "sys.exit(main())" not in proc.stderr, proc.stderr[-3000:]
        assert "lost the connection to dask scheduler" in errors[0] and "rerun the same command" in errors[0]
        assert 30 <= seen[-1] < 120, seen[-1]  # killed while preprocess still had frames to do
        cluster.stop()  # restart everything, as after a crash of the head node
        address = cluster.start()
        proc = _run(str(capture), "--work", str(work), "--scheduler", address, env=env)
        assert proc.returncode == 0, proc.stderr[-3000:]
    finally:
        cluster.stop()
    assert len(list(frames.rglob("*.exr"))) == 120
    assert tree_hash(work) == tree_hash(local)
