"""The stage runner: validate -> preprocess -> calibrate -> split -> shard as dask batch work, then train ->
eval as the training step (in this process or under torchrun). Finished stages are skipped on a rerun when
their record matches the current config and inputs; a changed config or changed upstream outputs reruns the
stage (from a clean slate) and, through the fingerprints, everything downstream.
"""

from __future__ import annotations

import contextlib
import inspect
import json
import os
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from lightstage.atomic import write_json_atomic
from lightstage.errors import LightstageError
from lightstage.pipelines import records
from lightstage.pipelines.config import PipelineConfig, config_as_data, config_hash, validate_pipeline_config
from lightstage.pipelines.stages import BATCH_STAGES, SPECS, STAGE_ORDER, StageImpl
from lightstage.workdir import WorkDir

MAX_SUMMARY_CHARS = 20_000


@dataclass
class StageResult:
    """What happened to one stage in this run."""

    stage: str
    status: str  # "ran" | "skipped" | "failed"
    reason: str
    seconds: float = 0.0
    summary: dict[str, Any] = field(default_factory=dict)


def select_stages(
    from_stage: str | None = None, only: str | None = None, to_stage: str | None = None
) -> tuple[list[str], bool]:
    """The stages to consider and whether they are forced (run even when up to date).

    `--from S` forces S and everything after it, `--only S` forces S alone; `--to S` stops after S (not forced)."""
    for flag, value in (("--from", from_stage), ("--only", only), ("--to", to_stage)):
        if value is not None and value not in STAGE_ORDER:
            raise LightstageError(f"{flag}: unknown stage {value!r} (stages: {', '.join(STAGE_ORDER)})")
    if only and (from_stage or to_stage):
        raise LightstageError("--only cannot be combined with --from or --to")
    if only:
        return [only], True
    start = STAGE_ORDER.index(from_stage) if from_stage else 0
    stop = STAGE_ORDER.index(to_stage) + 1 if to_stage else len(STAGE_ORDER)
    if stop <= start:
        raise LightstageError(f"--to {to_stage} comes before --from {from_stage}")
    return list(STAGE_ORDER[start:stop]), bool(from_stage)


class PipelineRunner:
    """Runs the selected stages of one work directory; dask is started only when a batch stage must run."""

    def __init__(
        self,
        work: WorkDir,
        config: PipelineConfig,
        *,
        client: Any = None,
        progress: bool = True,
        log: Callable[[str], None] | None = None,
    ) -> None:
        self.work = work
        self.config = config
        self.progress = progress
        self.log = log or (lambda msg: print(msg, flush=True))
        self._client = client
        self._own_client: contextlib.ExitStack | None = None
        self._fp_cache: dict[str, records.Fingerprint] = {}
        self._capture_fp: dict[str, Any] | None = None

    # ---- fingerprints ----
    def capture_fingerprint(self) -> dict[str, Any]:
        if self._capture_fp is None:
            root = self.work.capture_path()
            self._capture_fp = {"path": str(root), **records.fingerprint([root]).to_dict()}
        return self._capture_fp

    def outputs_fingerprint(self, name: str) -> records.Fingerprint:
        if name not in self._fp_cache:
            self._fp_cache[name] = records.fingerprint(SPECS[name].outputs(self.work))
        return self._fp_cache[name]

    def inputs_of(self, stage: str) -> dict[str, Any]:
        """The capture and every upstream stage's record config hash and current outputs."""
        upstream: dict[str, Any] = {}
        for name in STAGE_ORDER[: STAGE_ORDER.index(stage)]:
            rec = records.read_record(self.work, name)
            upstream[name] = {
                "config_hash": rec.get("config_hash") if rec else None,
                "outputs": self.outputs_fingerprint(name).digest,
            }
        return {"capture": self.capture_fingerprint(), "upstream": upstream}

    # ---- execution ----
    def client(self) -> Any:
        """The dask client (started on first use); None when `cluster.workers` is 0 (run in this process)."""
        if self._client is None and (self.config.cluster.scheduler or self.config.cluster.workers > 0):
            from lightstage.pipelines.cluster import dask_client

            self._own_client = contextlib.ExitStack()
            self._client = self._own_client.enter_context(dask_client(self.config.cluster))
        return self._client

    def close_client(self) -> None:
        if self._own_client is not None:
            self._own_client.close()
            self._own_client = None
            self._client = None

    def run(
        self,
        from_stage: str | None = None,
        only: str | None = None,
        clean: bool = False,
        to_stage: str | None = None,
    ) -> list[StageResult]:
        """Run the pipeline; returns one StageResult per selected stage. Raises LightstageError on failure."""
        selected, forced = select_stages(from_stage, only, to_stage)
        impls = {name: self.config.stage_impl(name) for name in selected}
        # Validate every selected stage's config before any work starts.
        configs = {name: self.config.stage_config(name, impls[name]) for name in selected}
        first = STAGE_ORDER.index(selected[0])
        for name in STAGE_ORDER[:first]:
            rec = records.read_record(self.work, name)
            if not rec or rec.get("status") != "done":
                self.log(
                    f"warning: {name} has no finished record in {self.work.root}; {selected[0]} may lack inputs"
                )
        results: list[StageResult] = []
        try:
            for i, name in enumerate(selected, 1):
                if name not in BATCH_STAGES:
                    self.close_client()  # the training step gets the machine to itself
                result = self._run_stage(impls[name], configs[name], forced, clean, f"[{i}/{len(selected)}]")
                results.append(result)
        finally:
            self.close_client()
        return results

    def _run_stage(
        self,
        impl: StageImpl,
        config: Any,
        forced: bool,
        clean: bool,
        tag: str,
    ) -> StageResult:
        name = impl.spec.name
        chash = config_hash(config, impl.where)
        inputs = self.inputs_of(name)
        input_key = _digest(inputs)
        rec = records.read_record(self.work, name)
        stale = rec is not None and (rec.get("config_hash") != chash or rec.get("input_key") != input_key)
        if rec and rec.get("status") == "done" and not stale and not forced:
            if rec.get("outputs", {}).get("digest") == self.outputs_fingerprint(name).digest:
                self.log(f"{tag} {name}: up to date (skipped)")
                return StageResult(name, "skipped", "up to date", 0.0, rec.get("summary", {}))
            reason = "outputs changed since the last run"
        elif forced:
            reason = "forced (--from/--only)"
        elif rec is None:
            reason = "no finished record"
        elif stale:
            reason = "config changed" if rec.get("config_hash") != chash else "inputs changed"
        else:
            reason = "previous attempt did not finish"
        if stale or (forced and clean):
            records.invalidate(self.work, name, impl.spec.outputs(self.work))
            reason += "; previous outputs removed"
        self.log(f"{tag} {name}: running ({reason})")
        self._fp_cache.pop(name, None)
        started = records.now_iso()
        t0 = time.perf_counter()
        try:
            summary = self._call(impl, config, name in BATCH_STAGES)
        except BaseException as e:
            seconds = time.perf_counter() - t0
            self._fp_cache.pop(name, None)
            if not isinstance(e, KeyboardInterrupt | SystemExit):
                records.write_record(
                    self.work,
                    name,
                    {
                        "stage": name,
                        "status": "failed",
                        "implementation": impl.where,
                        "config_hash": chash,
                        "input_key": input_key,
                        "started": started,
                        "finished": records.now_iso(),
                        "seconds": round(seconds, 3),
                        "error": f"{type(e).__name__}: {e}",
                    },
                )
            if isinstance(e, LightstageError):
                raise LightstageError(f"stage {name} failed: {e}") from e
            raise
        seconds = time.perf_counter() - t0
        self._fp_cache.pop(name, None)
        outputs = self.outputs_fingerprint(name)
        summary = _small(summary)
        report = records.read_report(records.report_path(self.work, name))
        if report is None:
            self.log(
                f"warning: {name} wrote no {records.report_path(self.work, name)}; the pipeline record stands alone"
            )
        record = {
            "stage": name,
            "status": "done",
            "implementation": impl.where,
            "config_hash": chash,
            "config": config_as_data(config),
            "inputs": inputs,
            "input_key": input_key,
            "outputs": outputs.to_dict(),
            "started": started,
            "finished": records.now_iso(),
            "seconds": round(seconds, 3),
            "summary": summary,
            **records.summarise_report(report, summary),
        }
        records.write_record(self.work, name, record)
        errors = record.get("errors", 0)
        extra = f", {errors} error(s) recorded in {records.report_path(self.work, name)}" if errors else ""
        self.log(f"{tag} {name}: done in {seconds:.1f} s{extra}")
        return StageResult(name, "ran", reason, seconds, summary)

    def _call(self, impl: StageImpl, config: Any, batch: bool) -> dict[str, Any]:
        if impl.spec.name == "train" and self.config.launch.launcher == "torchrun":
            return self._train_torchrun(impl)
        client = self.client() if batch else None
        kwargs: dict[str, Any] = {}
        params = inspect.signature(impl.run).parameters
        if "client" in params:
            kwargs["client"] = client
        if "progress" in params:
            kwargs["progress"] = self.progress
        out = impl.run(self.work, config, **kwargs)
        return out if isinstance(out, dict) else {"result": repr(out)}

    def _train_torchrun(self, impl: StageImpl) -> dict[str, Any]:
        """Train under torchrun (one process per GPU); rank 0 writes outputs and the report."""
        launch = self.config.launch
        spec_file = self.work.root / "reports" / ".train-launch.json"
        write_json_atomic(
            spec_file,
            {"section": self.config.stages.get("train", {}), "entry": self.config.entry_points.get("train")},
        )
        cmd = [
            launch.torchrun,
            "--standalone",
            f"--nproc_per_node={launch.nproc_per_node}",
            "-m",
            "lightstage.pipelines.runner",
            "train-rank",
            str(self.work.root),
            str(spec_file),
        ]
        self.log("training under: " + " ".join(cmd))
        try:
            proc = subprocess.run(cmd, check=False)
        except FileNotFoundError:
            raise LightstageError(
                f"launch.torchrun: {launch.torchrun!r} not found (is PyTorch installed?)"
            ) from None
        if proc.returncode != 0:
            raise LightstageError(f"torchrun exited with status {proc.returncode}")
        report = records.read_report(records.report_path(self.work, "train")) or {}
        return {k: v for k, v in report.items() if k != records.RECORD_KEY}


def run_pipeline(
    work: WorkDir,
    config: PipelineConfig,
    *,
    capture: str | os.PathLike[str] | None = None,
    from_stage: str | None = None,
    only: str | None = None,
    to_stage: str | None = None,
    clean: bool = False,
    client: Any = None,
    progress: bool = True,
    log: Callable[[str], None] | None = None,
) -> list[StageResult]:
    """Run the pipeline on `work` (writing WORK/capture.txt first when `capture` is given)."""
    capture = capture or config.capture
    validate_pipeline_config(config, capture if capture is not None else work.capture_path())
    work.root.mkdir(parents=True, exist_ok=True)
    if capture is not None:
        work.link_capture(capture)
    else:
        work.capture_path()
    runner = PipelineRunner(work, config, client=client, progress=progress, log=log)
    return runner.run(from_stage=from_stage, only=only, clean=clean, to_stage=to_stage)


def _digest(obj: Any) -> str:
    import hashlib

    return hashlib.sha256(json.dumps(obj, sort_keys=True).encode()).hexdigest()[:16]


def _small(summary: Any) -> dict[str, Any]:
    """The stage's summary, kept small in the record (large ones are truncated to their keys)."""
    if not isinstance(summary, dict):
        summary = {"result": repr(summary)}
    text = json.dumps(summary, default=str)
    if len(text) <= MAX_SUMMARY_CHARS:
        return json.loads(text)
    return {"truncated": True, "keys": sorted(map(str, summary))}


def _train_rank_main(work_root: str, spec_file: str) -> int:
    """Entry of each torchrun process: resolve the train stage and run it (the stage handles DDP ranks)."""
    from lightstage.pipelines.stages import resolve_stage

    spec = json.loads(Path(spec_file).read_text())
    impl = resolve_stage("train", spec.get("entry"))
    config = impl.make_config(spec.get("section") or {})
    rank = int(os.environ.get("RANK", "0"))
    kwargs: dict[str, Any] = {}
    params = inspect.signature(impl.run).parameters
    if "progress" in params:
        kwargs["progress"] = rank == 0
    impl.run(WorkDir.at(work_root), config, **kwargs)
    return 0


if __name__ == "__main__":
    if len(sys.argv) == 4 and sys.argv[1] == "train-rank":
        sys.exit(_train_rank_main(sys.argv[2], sys.argv[3]))
    print("usage: python -m lightstage.pipelines.runner train-rank WORK SPEC.json", file=sys.stderr)
    sys.exit(2)
