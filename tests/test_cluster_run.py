"""The cluster path run as on a cluster: a `dask scheduler` and two `dask worker` processes on loopback,
`lightstage run ... --scheduler tcp://127.0.0.1:PORT --to shard` on the tiny simulated capture, one worker
killed (SIGKILL) mid-preprocess; the outputs equal a local in-process run's file by file (bench/tree_hash.py)."""

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

CONFIG = "calibrate:\n  num_threads: 1\n"  # pycolmap is deterministic with one thread only


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def lightstage(*args: str, env: dict[str, str]) -> subprocess.CompletedProcess:
    cmd = [sys.executable, "-m", "lightstage.pipelines.cli", *args]
    return subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=300)


def wait_for_workers(address: str, n: int, timeout_s: float = 60.0) -> None:
    from distributed import Client

    with Client(address, timeout="30s") as client:
        client.wait_for_workers(n, timeout=timeout_s)


@pytest.mark.slow
def test_external_scheduler_with_a_killed_worker_matches_a_local_run(
    tmp_path: Path, tiny_capture: Path, kill_process_when
) -> None:
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONUNBUFFERED": "1"}
    cfg = tmp_path / "p.yaml"
    cfg.write_text(CONFIG)
    local = tmp_path / "local"
    proc = lightstage(
        "run", str(tiny_capture), "--work", str(local), "--config", str(cfg), "--to", "shard", "--workers", "0",
        "--quiet", env=env,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr

    port = free_port()
    address = f"tcp://127.0.0.1:{port}"
    dask = [sys.executable, "-m"]
    started: list[subprocess.Popen] = []
    logs = tmp_path / "logs"
    logs.mkdir()

    def start(name: str, cmd: list[str]) -> subprocess.Popen:
        out = open(logs / f"{name}.log", "w")  # noqa: SIM115 - closed with the process
        p = subprocess.Popen(cmd, env=env, stdout=out, stderr=subprocess.STDOUT, start_new_session=True)
        started.append(p)
        return p

    try:
        start(
            "scheduler",
            [
                *dask,
                "distributed.cli.dask_scheduler",
                "--host",
                "127.0.0.1",
                "--port",
                str(port),
                "--no-dashboard",
            ],
        )
        workers = [
            start(
                f"worker{i}",
                [
                    *dask,
                    "distributed.cli.dask_worker",
                    address,
                    "--nthreads",
                    "1",
                    "--no-nanny",
                    "--host",
                    "127.0.0.1",
                    "--no-dashboard",
                    "--memory-limit",
                    "2GiB",
                ],
            )  # fmt: skip
            for i in range(2)
        ]
        wait_for_workers(address, 2)
        work = tmp_path / "cluster"
        frames = work / "preprocess" / "frames"
        seen: list[int] = []

        def mid_preprocess() -> bool:
            n = sum(1 for _ in frames.rglob("*.exr")) if frames.is_dir() else 0
            seen.append(n)
            return n >= 60

        with kill_process_when(workers[0].pid, mid_preprocess, timeout_s=120) as killer:
            proc = lightstage(
                "run", str(tiny_capture), "--work", str(work), "--config", str(cfg), "--to", "shard",
                "--scheduler", address, "--quiet", env=env,
            )  # fmt: skip
        assert proc.returncode == 0, proc.stderr[-3000:]
        assert killer.killed and workers[0].wait(timeout=30) == -9
        assert 60 <= seen[-1] < 432, seen[-1]  # killed while preprocess still had frames to do
        assert workers[1].poll() is None  # the other worker finished the job
    finally:
        for p in reversed(started):
            if p.poll() is None:
                p.terminate()
        for p in started:
            try:
                p.wait(timeout=20)
            except subprocess.TimeoutExpired:
                p.kill()
    assert tree_hash(work) == tree_hash(local)
