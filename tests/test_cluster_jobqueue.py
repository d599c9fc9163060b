"""Clusters labs have: `cluster: {kind: slurm|pbs, ...}` in the pipeline config. dask-jobqueue writes each job's
batch script as text, so the script is checked here without SLURM or PBS (no job is submitted)."""

from __future__ import annotations

import pytest

from lightstage.config import ConfigError
from lightstage.pipelines.cli import main
from lightstage.pipelines.cluster import ClusterSettings, job_script
from lightstage.pipelines.config import PipelineConfig

SLURM = """\
capture: /data/candle
work: /scratch/candle-work
cluster:
  kind: slurm
  jobs: 4
  cores: 32
  memory: 128GB
  queue: cpu
  account: vislab
  walltime: "08:00:00"
  job_extra: ["--exclusive"]
  prologue: ["source /opt/lightstage/venv/bin/activate"]
  python: /opt/lightstage/venv/bin/python
  local_directory: $TMPDIR
"""


def test_slurm_job_script_from_the_pipeline_config(tmp_path, capsys):
    path = tmp_path / "cluster.yaml"
    path.write_text(SLURM)
    assert main(["config", "job-script", str(path)]) == 0
    script = capsys.readouterr().out
    lines = script.splitlines()
    assert lines[0] == "#!/usr/bin/env bash"
    for directive in ("-p cpu", "-A vislab", "--cpus-per-task=32", "-t 08:00:00", "--exclusive"):
        assert f"#SBATCH {directive}" in lines, directive
    assert any(ln.startswith("#SBATCH --mem=") for ln in lines)
    # the same per-process settings as a local worker, then the lab's own prologue, then the workers
    exports = [ln for ln in lines if ln.startswith("export ")]
    assert "export OMP_NUM_THREADS=1" in exports and "export MALLOC_ARENA_MAX=1" in exports
    assert lines.index(exports[-1]) < lines.index("source /opt/lightstage/venv/bin/activate")
    worker = next(ln for ln in lines if "distributed.cli.dask_worker" in ln)
    assert worker.startswith("/opt/lightstage/venv/bin/python -m distributed.cli.dask_worker tcp://")
    assert "--nthreads 1" in worker and "--nworkers 32" in worker and "--local-directory $TMPDIR" in worker


def test_pbs_job_script_and_threads_per_worker():
    s = ClusterSettings(
        kind="pbs", cores=8, threads_per_worker=2, memory="32GB", queue="workq", walltime="01:00:00"
    )
    script = job_script(s)
    assert "#PBS -q workq" in script and "#PBS -l walltime=01:00:00" in script
    assert "ncpus=8" in script and "export OMP_NUM_THREADS=2" in script
    assert "--nthreads 2" in script and "--nworkers 4" in script


@pytest.mark.parametrize(
    ("cluster", "message"),
    [
        ({"kind": "local", "jobs": 3}, "cluster.jobs: only for kind slurm or pbs"),
        ({"kind": "slurmm"}, "did you mean 'slurm'"),
        (
            {"kind": "pbs", "scheduler": "tcp://head:8786"},
            "cluster.scheduler: kind pbs starts its own scheduler",
        ),
        ({"kind": "slurm", "jobs": 0}, "cluster.jobs: expected an integer >= 1"),
    ],
)
def test_cluster_settings_are_checked(cluster, message):
    with pytest.raises(ConfigError, match=message):
        PipelineConfig.from_dict({"cluster": cluster}, "p.yaml")


def test_local_config_has_no_job_script(tmp_path, capsys):
    path = tmp_path / "local.yaml"
    path.write_text("cluster: {workers: 2}\n")
    assert main(["config", "job-script", str(path)]) == 2
    assert "cluster.kind is local" in capsys.readouterr().err
