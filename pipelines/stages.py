"""The stage table: for every stage of the pipeline, its run function and config class (imported directly,
so an IDE or grep follows `run_validate` to here and a broken stage module fails its import with its own
name), the stages whose outputs it reads, and the paths it writes.

Every run function has the stage API signature `run_X(work, config, executor=None, progress=True) -> dict`:
`executor` (lightstage.executor) runs the stage's per-item work, None meaning an in-process loop. The runner
(pipelines/runner.py) alone decides whether a stage is up to date, from these inputs and outputs.
`entry_points` in a pipeline config can point a stage at another implementation ("module:function") with
the same signature (tests use fakes).
"""

from __future__ import annotations

import dataclasses
import importlib
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from lightstage.calibration.config import CalibrateConfig
from lightstage.calibration.run import run_calibrate
from lightstage.capture.validate import ValidateConfig, run_validate
from lightstage.dataset.bounds import BoundsConfig, run_bounds
from lightstage.dataset.shard_config import ShardConfig
from lightstage.dataset.shards import run_shard
from lightstage.dataset.split import SplitConfig, run_split
from lightstage.errors import LightstageError
from lightstage.preprocess.config import PreprocessConfig
from lightstage.preprocess.run import run_preprocess
from lightstage.training.config import EvalConfig, TrainConfig, load_config
from lightstage.training.evaluate import run_eval
from lightstage.training.train_stage import run_train
from lightstage.workdir import WorkDir

CAPTURE = "capture"  # the raw capture named in WORK/capture.txt, an input of its own


@dataclass(frozen=True)
class StageSpec:
    """One row of the stage table."""

    name: str
    run: Callable[..., dict]
    config_cls: type
    inputs: tuple[str, ...]  # CAPTURE and/or the earlier stages whose outputs this stage reads
    outputs: Callable[[WorkDir], tuple[Path, ...]]  # everything it writes (fingerprinted, removed when stale)
    expects: Callable[[WorkDir], tuple[Path, ...]]  # what must exist once it finished
    batch: bool = True  # batch work (the executor) vs the training step (local or torchrun)
    resumes: bool = False  # redoes only missing items when called again on partial or damaged outputs
    report: str = ""  # its report is WORK/reports/<report>.json (calibrate writes calibration.json)
    # An empty section passes config=None (the stage's own choice, e.g. eval's config stored with the
    # checkpoint) instead of the config class's defaults.
    none_when_empty: bool = False
    # `config: NAME` in the section loads a named base config: loader(name, other keys) (train: tiny, cpu)
    named_configs: Callable[[str, dict[str, Any]], Any] | None = None

    @property
    def report_stem(self) -> str:
        return self.report or self.name


def _paths(*names: str) -> Callable[[WorkDir], tuple[Path, ...]]:
    """outputs/expects as WorkDir attribute names, e.g. _paths("split") -> (work.split,)."""
    return lambda w: tuple(getattr(w, n) for n in names)


def _bounds_outputs(w: WorkDir) -> tuple[Path, ...]:
    return (w.bounds, w.root / "bounds.png")


def _expected_shards(w: WorkDir) -> tuple[Path, ...]:
    return (w.shards_dir / "manifest.json",)


STAGES: tuple[StageSpec, ...] = (
    StageSpec(
        "validate",
        run_validate,
        ValidateConfig,
        (CAPTURE,),
        _paths("manifest"),
        _paths("manifest"),
        resumes=True,
    ),
    StageSpec(
        "preprocess",
        run_preprocess,
        PreprocessConfig,
        (CAPTURE, "validate"),
        _paths("preprocess_dir"),
        _paths("preprocess_dir"),
        resumes=True,
    ),
    StageSpec(
        "calibrate",
        run_calibrate,
        CalibrateConfig,
        (CAPTURE, "preprocess"),
        _paths("calibration_dir"),
        _paths("calibration"),
        report="calibration",
    ),
    StageSpec("split", run_split, SplitConfig, (CAPTURE, "preprocess"), _paths("split"), _paths("split")),
    StageSpec(
        "bounds",
        run_bounds,
        BoundsConfig,
        ("preprocess", "calibrate", "split"),
        _bounds_outputs,
        _paths("bounds"),
    ),
    StageSpec(
        "shard",
        run_shard,
        ShardConfig,
        ("preprocess", "calibrate", "split", "bounds"),
        _paths("shards_dir"),
        _expected_shards,
    ),
    StageSpec(
        "train",
        run_train,
        TrainConfig,
        ("shard", "bounds"),
        _paths("train_dir"),
        _paths("train_dir"),
        batch=False,
        named_configs=load_config,
    ),
    StageSpec(
        "eval",
        run_eval,
        EvalConfig,
        ("train", "shard"),
        _paths("eval_dir"),
        _paths("eval_dir"),
        batch=False,
        none_when_empty=True,
    ),
)

SPECS: dict[str, StageSpec] = {s.name: s for s in STAGES}
# The stages in pipeline order; data flows left to right only.
STAGE_ORDER: tuple[str, ...] = tuple(s.name for s in STAGES)
# Stages that run as batch work through the executor; the rest run afterwards as the training step.
BATCH_STAGES: tuple[str, ...] = tuple(s.name for s in STAGES if s.batch)
TRAINING_STAGES: tuple[str, ...] = tuple(s.name for s in STAGES if not s.batch)


def upstream(name: str) -> list[str]:
    """Every stage `name` depends on, directly or through its inputs, in pipeline order."""
    seen: set[str] = set()
    todo = [i for i in SPECS[name].inputs if i != CAPTURE]
    while todo:
        s = todo.pop()
        if s not in seen:
            seen.add(s)
            todo += [i for i in SPECS[s].inputs if i != CAPTURE]
    return [s for s in STAGE_ORDER if s in seen]


@dataclass(frozen=True)
class StageImpl:
    """A stage as it runs: the table's row with its run function (or an `entry_points` replacement)."""

    spec: StageSpec
    run: Callable[..., dict]
    config_cls: type | None
    where: str  # "module:function", recorded in the run record

    def make_config(self, section: dict[str, Any]) -> Any:
        """The stage's typed config from its YAML section (the config class's from_dict names bad keys).

        An empty section gives None where the stage defines None as its own choice (eval: the config stored
        with the checkpoint); `config: NAME` loads a named base config (train: {config: tiny})."""
        section = dict(section)
        if not section and self.spec.none_when_empty and self.run is self.spec.run:
            return None
        if self.config_cls is None:
            if section:
                raise LightstageError(
                    f"{self.spec.name}: this stage takes no parameters (got {sorted(section)})"
                )
            return None
        names = (
            {f.name for f in dataclasses.fields(self.config_cls)}
            if dataclasses.is_dataclass(self.config_cls)
            else set()
        )
        if "config" in section and "config" not in names:
            if self.spec.named_configs is None:
                raise LightstageError(f"{self.spec.name}.config: this stage has no named base configs")
            base = section.pop("config")
            if not isinstance(base, str):
                raise LightstageError(
                    f"{self.spec.name}.config: expected a config name or path, got {base!r}"
                )
            return self.spec.named_configs(base, section)
        return self.config_cls.from_dict(section)


def resolve_stage(name: str, entry_point: str | None = None) -> StageImpl:
    """The stage `name` from the table, or `entry_point` ("module:function", same signature) in its place
    (its config class: the function's module's `config_class` attribute if any, else the table's)."""
    spec = SPECS[name]
    if not entry_point:
        return StageImpl(spec, spec.run, spec.config_cls, f"{spec.run.__module__}:{spec.run.__name__}")
    mod_name, _, fn_name = entry_point.partition(":")
    try:
        module = importlib.import_module(mod_name)
    except ModuleNotFoundError as e:
        if e.name != mod_name:
            raise  # the module exists but one of its own imports is broken: show that
        raise LightstageError(f"entry_points.{name}: no module {mod_name!r}") from None
    fn = getattr(module, fn_name or f"run_{name}", None)
    if not callable(fn):
        raise LightstageError(f"entry_points.{name}: {mod_name} has no function {fn_name or f'run_{name}'!r}")
    config_cls = getattr(module, "CONFIG_CLASSES", {}).get(name, spec.config_cls)
    return StageImpl(spec, fn, config_cls, f"{mod_name}:{fn.__name__}")


def available_stages(entry_points: dict[str, str] | None = None) -> dict[str, StageImpl | str]:
    """Every stage resolved (for `config show`); a bad entry point gives its error text instead."""
    out: dict[str, StageImpl | str] = {}
    for name in STAGE_ORDER:
        try:
            out[name] = resolve_stage(name, (entry_points or {}).get(name))
        except LightstageError as e:
            out[name] = str(e)
    return out
