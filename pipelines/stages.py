"""The stage graph and how the pipeline finds each stage's entry point and config class.

Every stage package exposes `run_<stage>(work, config, client=None, progress=True) -> dict` and a config
dataclass with `from_dict` (the stage API convention). The pipeline finds them by name inside the package, so
a stage module can be renamed without touching the pipeline; `entry_points` in the pipeline config can point a
stage at another implementation ("module:function").
"""

from __future__ import annotations

import importlib
import inspect
import pkgutil
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from lightstage.errors import LightstageError
from lightstage.workdir import WorkDir

# The stages in pipeline order; data flows left to right only.
STAGE_ORDER: tuple[str, ...] = ("validate", "preprocess", "calibrate", "split", "shard", "train", "eval")
# Stages that run as dask batch work; the rest run afterwards as the training step (local or torchrun).
BATCH_STAGES: tuple[str, ...] = ("validate", "preprocess", "calibrate", "split", "shard")
TRAINING_STAGES: tuple[str, ...] = ("train", "eval")


@dataclass(frozen=True)
class StageSpec:
    """Where a stage lives, the modules to look in first, its config class names, and what it writes."""

    name: str
    package: str
    preferred_modules: tuple[str, ...]
    config_names: tuple[str, ...]
    outputs: Callable[[WorkDir], tuple[Path, ...]]
    # An empty section passes config=None (the stage's own choice, e.g. eval's config stored with the
    # checkpoint) instead of the config class's defaults.
    none_when_empty: bool = False
    # The stage's own report is WORK/reports/<report>.json (calibrate writes calibration.json).
    report: str = ""

    @property
    def function(self) -> str:
        return f"run_{self.name}"

    @property
    def report_stem(self) -> str:
        return self.report or self.name


def _outputs_validate(w: WorkDir) -> tuple[Path, ...]:
    return (w.manifest,)


def _outputs_preprocess(w: WorkDir) -> tuple[Path, ...]:
    return (w.preprocess_dir,)


def _outputs_calibrate(w: WorkDir) -> tuple[Path, ...]:
    return (w.calibration_dir,)


def _outputs_split(w: WorkDir) -> tuple[Path, ...]:
    return (w.split,)


def _outputs_shard(w: WorkDir) -> tuple[Path, ...]:
    return (w.bounds, w.shards_dir)


def _outputs_train(w: WorkDir) -> tuple[Path, ...]:
    return (w.train_dir,)


def _outputs_eval(w: WorkDir) -> tuple[Path, ...]:
    return (w.eval_dir,)


SPECS: dict[str, StageSpec] = {
    s.name: s
    for s in (
        StageSpec(
            "validate",
            "lightstage.capture",
            ("validate", "validation", "manifest"),
            ("ValidateConfig", "ValidationConfig"),
            _outputs_validate,
        ),
        StageSpec(
            "preprocess",
            "lightstage.preprocess",
            ("stage", "run", "pipeline", "preprocess"),
            ("PreprocessConfig",),
            _outputs_preprocess,
        ),
        StageSpec(
            "calibrate",
            "lightstage.calibration",
            ("calibrate", "stage", "run", "pipeline"),
            ("CalibrateConfig", "CalibrationConfig"),
            _outputs_calibrate,
            report="calibration",
        ),
        StageSpec("split", "lightstage.dataset", ("split", "splits"), ("SplitConfig",), _outputs_split),
        StageSpec(
            "shard", "lightstage.dataset", ("shard", "shards", "sharding"), ("ShardConfig",), _outputs_shard
        ),
        StageSpec(
            "train",
            "lightstage.training",
            ("train", "trainer", "stage"),
            ("TrainConfig", "TrainingConfig"),
            _outputs_train,
        ),
        StageSpec(
            "eval",
            "lightstage.training",
            ("eval", "evaluate", "evaluation", "stage"),
            ("EvalConfig", "EvaluationConfig"),
            _outputs_eval,
            none_when_empty=True,
        ),
    )
}

_SKIP_MODULES = {"cli", "use_cli", "__main__"}


@dataclass(frozen=True)
class StageImpl:
    """A resolved stage: its entry function and config class (None when the stage has no config class)."""

    spec: StageSpec
    run: Callable[..., dict]
    config_cls: type | None
    where: str  # "module:function", recorded in the run record

    def make_config(self, section: dict[str, Any]) -> Any:
        """The stage's typed config from its YAML section (the stage's from_dict validates and names keys).

        An empty section gives None where the stage defines None as its own choice (eval: the config stored
        with the checkpoint). A `config: NAME` key loads a named base config
        through the stage module's `load_config(name, overrides)` (e.g. train: {config: tiny})."""
        section = dict(section)
        if not section and self.spec.none_when_empty and _config_default_is_none(self.run):
            return None
        if self.config_cls is None:
            if section:
                raise LightstageError(
                    f"{self.spec.name}: this stage takes no parameters (got {sorted(section)})"
                )
            return None
        if "config" in section and "config" not in _field_names(self.config_cls):
            loader = getattr(importlib.import_module(self.config_cls.__module__), "load_config", None)
            if loader is None:
                raise LightstageError(f"{self.spec.name}.config: this stage has no named base configs")
            base = section.pop("config")
            if not isinstance(base, str):
                raise LightstageError(
                    f"{self.spec.name}.config: expected a config name or path, got {base!r}"
                )
            return loader(base, section)
        if hasattr(self.config_cls, "from_dict"):
            return self.config_cls.from_dict(section)
        try:
            return self.config_cls(**section)
        except TypeError as e:
            raise LightstageError(f"{self.spec.name}: {e}") from None


def _field_names(cls: type) -> set[str]:
    import dataclasses

    return {f.name for f in dataclasses.fields(cls)} if dataclasses.is_dataclass(cls) else set()


def _config_default_is_none(fn: Callable[..., Any]) -> bool:
    params = list(inspect.signature(fn).parameters.values())
    return len(params) >= 2 and params[1].default is None


def _import(name: str) -> Any | None:
    try:
        return importlib.import_module(name)
    except ImportError:
        return None


def _candidate_modules(spec: StageSpec) -> list[str]:
    pkg = _import(spec.package)
    if pkg is None:
        return []
    names = [spec.package] + [f"{spec.package}.{m}" for m in spec.preferred_modules]
    for info in pkgutil.iter_modules(getattr(pkg, "__path__", [])):
        if info.name not in _SKIP_MODULES and not info.name.startswith("_"):
            full = f"{spec.package}.{info.name}"
            if full not in names:
                names.append(full)
    return names


def _config_class(fn: Callable[..., Any], module: Any, spec: StageSpec) -> type | None:
    """The config class: the annotation of the entry function's `config` parameter, else a known name."""
    params = list(inspect.signature(fn).parameters.values())
    if len(params) >= 2:
        ann = params[1].annotation
        if isinstance(ann, type) and ann is not inspect.Parameter.empty:
            return ann
        if isinstance(ann, str):
            for name in ann.replace("None", "").replace("|", " ").split():
                obj = getattr(module, name.strip("'\" "), None)
                if isinstance(obj, type):
                    return obj
    for where in (module, _import(f"{spec.package}.config")):
        for name in spec.config_names:
            obj = getattr(where, name, None) if where is not None else None
            if isinstance(obj, type):
                return obj
    return None


def resolve_stage(name: str, entry_point: str | None = None) -> StageImpl:
    """Find a stage's entry function and config class (or load `entry_point` = "module:function")."""
    spec = SPECS[name]
    if entry_point:
        mod_name, _, fn_name = entry_point.partition(":")
        module = _import(mod_name)
        fn = getattr(module, fn_name or spec.function, None) if module is not None else None
        if not callable(fn):
            raise LightstageError(f"entry_points.{name}: cannot import {entry_point!r}")
        return StageImpl(spec, fn, _config_class(fn, module, spec), f"{mod_name}:{fn.__name__}")
    for mod_name in _candidate_modules(spec):
        try:
            module = importlib.import_module(mod_name)
        except Exception:  # noqa: BLE001 - a module under construction must not hide the others
            continue
        fn = getattr(module, spec.function, None)
        if callable(fn):
            owner = importlib.import_module(getattr(fn, "__module__", mod_name) or mod_name)
            return StageImpl(spec, fn, _config_class(fn, owner, spec), f"{owner.__name__}:{spec.function}")
    raise LightstageError(
        f"stage {name!r} is not available: no {spec.function}() found in {spec.package} "
        f"(set entry_points.{name} in the pipeline config to point at one)"
    )


def available_stages(entry_points: dict[str, str] | None = None) -> dict[str, StageImpl | str]:
    """Every stage resolved, or the reason it is unavailable (for `config show` and error messages)."""
    out: dict[str, StageImpl | str] = {}
    for name in STAGE_ORDER:
        try:
            out[name] = resolve_stage(name, (entry_points or {}).get(name))
        except LightstageError as e:
            out[name] = str(e)
    return out
