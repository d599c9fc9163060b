"""The stage runner: validate -> preprocess -> calibrate -> split -> bounds -> shard as batch work through one
executor (built once per run: a dask LocalCluster, an existing scheduler, or an in-process loop), then train ->
eval as the training step (in this process or under torchrun).

Whether a stage is up to date is decided here and only here (`decide`): a finished stage is skipped on a
rerun when its record matches the current config, its inputs (the capture and its upstream stages' records
and outputs) and its own outputs; a changed config or input reruns it from a clean slate and, through the
fingerprints, everything downstream. A stage that could not produce every expected output is recorded as
`incomplete` with what is missing, the run exits non-zero, and the next run calls it again to redo exactly
that (stages resume: they skip the items they already wrote).
"""

from __future__ import annotations

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
from lightstage.errors import EnvironmentFault, LightstageError, StageIncomplete
from lightstage.executor import Executor, LoopExecutor
from lightstage.pipelines import records
from lightstage.pipelines.cluster import open_executor
from lightstage.pipelines.config import PipelineConfig, config_as_data, config_hash, validate_pipeline_config
from lightstage.pipelines.stages import SPECS, STAGE_ORDER, StageImpl, upstream
from lightstage.workdir import WorkDir

MAX_SUMMARY_CHARS = 20_000
MAX_MISSING_LISTED = 50


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


@dataclass(frozen=True)
class Decision:
    """Whether to run a stage, why, and whether its previous outputs must go first."""

    run: bool
    reason: str
    remove_outputs: bool = False


def decide(
    rec: dict[str, Any] | None,
    config_hash: str,
    input_key: str,
    outputs_digest: Callable[[], str],
    *,
    forced: bool = False,
    clean: bool = False,
    resumes: bool = False,
) -> Decision:
    """The one up-to-date decision. `rec`: the stage's last pipeline record; `outputs_digest()`: its outputs'
    fingerprint now. Outputs made with another config or other inputs are removed before it runs again, and so
    are changed outputs of a stage that does not resume item by item; a stage that did not finish (killed,
    failed, incomplete) is called again on what it left, which it resumes."""
    if rec is None:
        return Decision(True, "no finished record", forced and clean)
    if rec.get("config_hash") != config_hash:
        return Decision(True, "config changed", True)
    if rec.get("input_key") != input_key:
        return Decision(True, "inputs changed", True)
    if forced:
        return Decision(True, "forced (--from/--only)", clean)
    status = rec.get("status")
    if status == "done":
        if rec.get("outputs", {}).get("digest") == outputs_digest():
            return Decision(False, "up to date")
        return Decision(True, "outputs changed since the last run", not resumes)
    if status == "incomplete":
        return Decision(True, f"retrying {rec.get('missing_count', 0)} missing output(s)")
    return Decision(True, "previous attempt did not finish")


class PipelineRunner:
    """Runs the selected stages of one work directory; the executor is built when a batch stage must run
    (or given), closed before the training step."""

    def __init__(
        self,
        work: WorkDir,
        config: PipelineConfig,
        *,
        executor: Executor | None = None,
        progress: bool = True,
        log: Callable[[str], None] | None = None,
    ) -> None:
        self.work = work
        self.config = config
        self.progress = progress
        self.log = log or (lambda msg: print(msg, flush=True))
        self._executor = executor
        self._own_executor = False
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
        """The capture, and the record config hash and current outputs of every stage `stage` reads from
        (its inputs in the stage table and theirs, transitively)."""
        ups: dict[str, Any] = {}
        for name in upstream(stage):
            rec = records.read_record(self.work, name)
            ups[name] = {
                "config_hash": rec.get("config_hash") if rec else None,
                "outputs": self.outputs_fingerprint(name).digest,
            }
        return {"capture": self.capture_fingerprint(), "upstream": ups}

    # ---- execution ----
    def executor(self) -> Executor:
        """The run's executor for batch stages (built on first use from `cluster:`, then reused)."""
        if self._executor is None:
            self._executor = open_executor(self.config.cluster)
            self._own_executor = True
        return self._executor

    def close_executor(self) -> None:
        if self._own_executor and self._executor is not None:
            self._executor.close()
        if self._own_executor:
            self._executor = None
            self._own_executor = False

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
                if not SPECS[name].batch:
                    self.close_executor()  # the training step gets the machine to itself
                result = self._run_stage(impls[name], configs[name], forced, clean, f"[{i}/{len(selected)}]")
                results.append(result)
        finally:
            self.close_executor()
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
        d = decide(
            rec,
            chash,
            input_key,
            lambda: self.outputs_fingerprint(name).digest,
            forced=forced,
            clean=clean,
            resumes=impl.spec.resumes,
        )
        if not d.run:
            self.log(f"{tag} {name}: up to date (skipped)")
            return StageResult(name, "skipped", d.reason, 0.0, (rec or {}).get("summary", {}))
        reason = d.reason
        if d.remove_outputs:
            records.invalidate(self.work, name, impl.spec.outputs(self.work))
            reason += "; previous outputs removed"
        self.log(f"{tag} {name}: running ({reason})")
        self._fp_cache.pop(name, None)
        base = {"stage": name, "implementation": impl.where, "config_hash": chash, "input_key": input_key}
        started = records.now_iso()
        t0 = time.perf_counter()
        try:
            summary = self._call(impl, config)
            missing = _missing(self.work, impl, summary)
        except StageIncomplete as e:
            summary, missing = e.summary, e.missing or [str(e)]
        except BaseException as e:
            self._fp_cache.pop(name, None)
            if not isinstance(e, KeyboardInterrupt | SystemExit):
                records.write_record(
                    self.work, name, {**base, **_timing(started, t0), "status": "failed", "error": _line(e)}
                )
            if isinstance(e, EnvironmentFault):
                raise EnvironmentFault(f"stage {name} failed: {e}") from e
            if isinstance(e, LightstageError):
                raise LightstageError(f"stage {name} failed: {e}") from e
            raise
        self._fp_cache.pop(name, None)
        summary = _small(summary)
        report = records.read_report(records.report_path(self.work, name))
        if missing:
            records.write_record(
                self.work,
                name,
                {
                    **base,
                    **_timing(started, t0),
                    "status": "incomplete",
                    "missing_count": len(missing),
                    "missing": missing[:MAX_MISSING_LISTED],
                    "summary": summary,
                    **records.summarise_report(report, summary),
                },
            )
            shown = ", ".join(missing[:3]) + (", ..." if len(missing) > 3 else "")
            raise StageIncomplete(
                f"stage {name} incomplete: {len(missing)} expected output(s) missing ({shown}); it is not "
                f"recorded as done, the next run retries them (see {records.report_path(self.work, name)})",
                missing,
                summary,
            )
        if report is None:
            self.log(
                f"warning: {name} wrote no {records.report_path(self.work, name)}; the pipeline record stands alone"
            )
        timing = _timing(started, t0)
        record = {
            **base,
            "status": "done",
            "config": config_as_data(config),
            "inputs": inputs,
            "outputs": self.outputs_fingerprint(name).to_dict(),
            **timing,
            "summary": summary,
            **records.summarise_report(report, summary),
        }
        records.write_record(self.work, name, record)
        errors = record.get("errors", 0)
        extra = f", {errors} error(s) recorded in {records.report_path(self.work, name)}" if errors else ""
        self.log(f"{tag} {name}: done in {timing['seconds']:.1f} s{extra}")
        return StageResult(name, "ran", reason, timing["seconds"], summary)

    def _call(self, impl: StageImpl, config: Any) -> dict[str, Any]:
        """Run the stage with the stage API signature: run(work, config, executor=..., progress=...)."""
        if impl.spec.name == "train" and self.config.launch.launcher == "torchrun":
            return self._train_torchrun(impl)
        executor = self.executor() if impl.spec.batch else LoopExecutor()
        out = impl.run(self.work, config, executor=executor, progress=self.progress)
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
    executor: Executor | None = None,
    progress: bool = True,
    log: Callable[[str], None] | None = None,
) -> list[StageResult]:
    """Run the pipeline on `work` (writing WORK/capture.txt first when `capture` is given). `executor`: run
    the batch stages on it (default: one built from the config's `cluster:` for this run)."""
    capture = capture or config.capture
    validate_pipeline_config(config, capture if capture is not None else work.capture_path())
    work.root.mkdir(parents=True, exist_ok=True)
    if capture is not None:
        work.link_capture(capture)
    else:
        work.capture_path()
    runner = PipelineRunner(work, config, executor=executor, progress=progress, log=log)
    return runner.run(from_stage=from_stage, only=only, clean=clean, to_stage=to_stage)


def _digest(obj: Any) -> str:
    import hashlib

    return hashlib.sha256(json.dumps(obj, sort_keys=True).encode()).hexdigest()[:16]


def _missing(work: WorkDir, impl: StageImpl, summary: Any) -> list[str]:
    """Expected outputs that a stage which returned did not produce: the paths of the stage table's `expects`
    that do not exist, and what the stage itself lists under `missing` in its summary."""
    out = [str(p) for p in impl.spec.expects(work) if not p.exists()]
    listed = summary.get("missing") if isinstance(summary, dict) else None
    if isinstance(listed, list | tuple):
        out += [str(m) for m in listed]
    return out


def _timing(started: str, t0: float) -> dict[str, Any]:
    return {"started": started, "finished": records.now_iso(), "seconds": round(time.perf_counter() - t0, 3)}


def _line(e: BaseException) -> str:
    return f"{type(e).__name__}: {e}"


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
    impl.run(WorkDir.at(work_root), config, executor=LoopExecutor(), progress=rank == 0)
    return 0


if __name__ == "__main__":
    if len(sys.argv) == 4 and sys.argv[1] == "train-rank":
        sys.exit(_train_rank_main(sys.argv[2], sys.argv[3]))
    print("usage: python -m lightstage.pipelines.runner train-rank WORK SPEC.json", file=sys.stderr)
    sys.exit(2)
