"""The pipeline config: one YAML file with the capture, the work directory, how to execute (dask cluster,
training launcher) and every stage's parameters. Each stage section is validated by that stage's own config
class (`from_dict`), so messages name the key; `lightstage config show` prints the effective config.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any

import yaml

from lightstage.errors import LightstageError
from lightstage.pipelines.cluster import ClusterSettings
from lightstage.pipelines.stages import STAGE_ORDER, StageImpl, available_stages, resolve_stage

TOP_KEYS = ("capture", "work", "cluster", "launch", "demo", "entry_points", *STAGE_ORDER)
LAUNCHERS = ("local", "torchrun")


@dataclass(frozen=True)
class LaunchSettings:
    """How the training step runs: in this process, or `torchrun` with several processes (GPUs)."""

    launcher: str = "local"
    nproc_per_node: int = 1
    torchrun: str = "torchrun"  # the torchrun executable


@dataclass(frozen=True)
class DemoSettings:
    """What `lightstage demo` simulates: a simulator preset, seed and optional subsets (selector strings such
    as "0-11" or "0,3,5"; empty = all) of groups, cameras and lights."""

    preset: str = "small"
    seed: int = 0
    groups: str = ""
    cameras: str = ""
    lights: str = ""


@dataclass(frozen=True)
class PipelineConfig:
    """Everything one `lightstage run` needs; stage sections are raw mappings until resolved."""

    capture: str | None = None
    work: str | None = None
    cluster: ClusterSettings = field(default_factory=ClusterSettings)
    launch: LaunchSettings = field(default_factory=LaunchSettings)
    demo: DemoSettings = field(default_factory=DemoSettings)
    entry_points: dict[str, str] = field(default_factory=dict)
    stages: dict[str, dict[str, Any]] = field(default_factory=lambda: {s: {} for s in STAGE_ORDER})
    source: str = "<defaults>"

    @classmethod
    def from_dict(cls, data: Any, source: str = "<config>") -> PipelineConfig:
        """Validate a mapping (top-level keys, cluster/launch types); stage sections are checked by
        `stage_configs`. Errors name the file and the key."""
        if data is None:
            data = {}
        if not isinstance(data, dict):
            raise LightstageError(f"{source}: expected a mapping at the top level")
        for key in data:
            if key not in TOP_KEYS:
                raise LightstageError(f"{source}: {key}: unknown key (known: {', '.join(TOP_KEYS)})")
        capture = _opt_str(data, "capture", source)
        work = _opt_str(data, "work", source)
        cluster = _dataclass_from(ClusterSettings, data.get("cluster"), "cluster", source)
        if cluster.workers < 0:
            raise LightstageError(
                f"{source}: cluster.workers: expected an integer >= 0, got {cluster.workers}"
            )
        if cluster.threads_per_worker < 1:
            raise LightstageError(
                f"{source}: cluster.threads_per_worker: expected an integer >= 1, got {cluster.threads_per_worker}"
            )
        launch = _dataclass_from(LaunchSettings, data.get("launch"), "launch", source)
        if launch.launcher not in LAUNCHERS:
            raise LightstageError(
                f"{source}: launch.launcher: expected one of {', '.join(LAUNCHERS)}, got {launch.launcher!r}"
            )
        if launch.nproc_per_node < 1:
            raise LightstageError(f"{source}: launch.nproc_per_node: expected an integer >= 1")
        demo = _dataclass_from(DemoSettings, data.get("demo"), "demo", source)
        entry = data.get("entry_points") or {}
        if not isinstance(entry, dict) or not all(isinstance(v, str) for v in entry.values()):
            raise LightstageError(f"{source}: entry_points: expected a mapping of stage -> 'module:function'")
        for key in entry:
            if key not in STAGE_ORDER:
                raise LightstageError(f"{source}: entry_points.{key}: unknown stage")
        stages: dict[str, dict[str, Any]] = {}
        for name in STAGE_ORDER:
            section = data.get(name)
            if section is None:
                section = {}
            if not isinstance(section, dict):
                raise LightstageError(f"{source}: {name}: expected a mapping of parameters")
            stages[name] = dict(section)
        return cls(capture, work, cluster, launch, demo, dict(entry), stages, source)

    def with_overrides(self, **changes: Any) -> PipelineConfig:
        """A copy with top-level fields replaced (None values are ignored)."""
        return dataclasses.replace(self, **{k: v for k, v in changes.items() if v is not None})

    def with_cluster(self, **changes: Any) -> PipelineConfig:
        """A copy with cluster settings replaced (None values are ignored)."""
        cluster = dataclasses.replace(self.cluster, **{k: v for k, v in changes.items() if v is not None})
        return dataclasses.replace(self, cluster=cluster)

    def stage_impl(self, name: str) -> StageImpl:
        return resolve_stage(name, self.entry_points.get(name))

    def stage_config(self, name: str, impl: StageImpl | None = None) -> Any:
        """The stage's typed config from its section; the stage's error message is prefixed with the file."""
        impl = impl or self.stage_impl(name)
        try:
            return impl.make_config(self.stages.get(name, {}))
        except LightstageError as e:
            msg = str(e)
            prefix = f"{name}." if not msg.startswith(name) else ""
            raise LightstageError(f"{self.source}: {prefix}{msg}") from None

    def effective(self) -> dict[str, Any]:
        """The effective config as plain data: defaults filled in for every stage that is installed."""
        out: dict[str, Any] = {
            "capture": self.capture,
            "work": self.work,
            "cluster": dataclasses.asdict(self.cluster),
            "launch": dataclasses.asdict(self.launch),
            "demo": dataclasses.asdict(self.demo),
        }
        if self.entry_points:
            out["entry_points"] = dict(self.entry_points)
        for name, impl in available_stages(self.entry_points).items():
            if isinstance(impl, str):
                out[name] = {**self.stages.get(name, {}), "_unavailable": impl}
            else:
                out[name] = config_as_data(self.stage_config(name, impl))
        return out


def config_as_data(config: Any) -> Any:
    """A stage config as JSON-able data (dataclasses, paths, tuples, nested)."""
    if config is None:
        return {}
    if dataclasses.is_dataclass(config) and not isinstance(config, type):
        config = dataclasses.asdict(config)
    elif hasattr(config, "to_dict"):
        config = config.to_dict()
    return json.loads(json.dumps(config, default=_jsonable))


def _jsonable(obj: Any) -> Any:
    if isinstance(obj, os.PathLike):
        return os.fspath(obj)
    if isinstance(obj, set | frozenset):
        return sorted(obj)
    if hasattr(obj, "item"):
        return obj.item()
    if hasattr(obj, "tolist"):
        return obj.tolist()
    return repr(obj)


def config_hash(config: Any, implementation: str = "") -> str:
    """A stable hash of a stage's effective config (and which implementation ran it)."""
    payload = json.dumps({"config": config_as_data(config), "impl": implementation}, sort_keys=True)
    return hashlib.sha256(payload.encode()).hexdigest()[:16]


def _opt_str(data: dict[str, Any], key: str, source: str) -> str | None:
    value = data.get(key)
    if value is None:
        return None
    if not isinstance(value, str | os.PathLike):
        raise LightstageError(f"{source}: {key}: expected a path string, got {value!r}")
    return os.fspath(value)


def _dataclass_from(cls: type, section: Any, key: str, source: str) -> Any:
    """Build a flat dataclass of str/int/float/bool fields from a mapping, naming bad keys and types."""
    if section is None:
        return cls()
    if not isinstance(section, dict):
        raise LightstageError(f"{source}: {key}: expected a mapping")
    fields = {f.name: f for f in dataclasses.fields(cls)}
    kwargs: dict[str, Any] = {}
    defaults = cls()
    for name, value in section.items():
        if name not in fields:
            raise LightstageError(f"{source}: {key}.{name}: unknown key (known: {', '.join(fields)})")
        default = getattr(defaults, name)
        if value is None:
            if default is not None:
                raise LightstageError(f"{source}: {key}.{name}: must not be empty")
        elif isinstance(default, bool):
            if not isinstance(value, bool):
                raise LightstageError(f"{source}: {key}.{name}: expected true/false, got {value!r}")
        elif isinstance(default, int):
            if not isinstance(value, int) or isinstance(value, bool):
                raise LightstageError(f"{source}: {key}.{name}: expected an integer, got {value!r}")
        elif isinstance(default, float):
            if not isinstance(value, int | float) or isinstance(value, bool):
                raise LightstageError(f"{source}: {key}.{name}: expected a number, got {value!r}")
            value = float(value)
        elif not isinstance(value, str):
            raise LightstageError(f"{source}: {key}.{name}: expected a string, got {value!r}")
        kwargs[name] = value
    return cls(**kwargs)


def builtin_config_names() -> list[str]:
    """Names of the configs shipped in lightstage/pipelines/configs (e.g. default, demo)."""
    folder = resources.files("lightstage.pipelines") / "configs"
    return sorted(p.name[:-5] for p in folder.iterdir() if p.name.endswith(".yaml"))


def load_pipeline_config(path: str | os.PathLike[str] | None = None) -> PipelineConfig:
    """Read a pipeline config file (or a built-in name such as `demo`; None gives `default`).

    Relative `capture`/`work` paths in a file are resolved against the file's folder."""
    if path is None:
        path = "default"
    p = Path(path)
    if not p.exists() and not p.suffix and str(path) in builtin_config_names():
        text = (resources.files("lightstage.pipelines") / "configs" / f"{path}.yaml").read_text()
        return PipelineConfig.from_dict(_parse_yaml(text, f"<builtin {path}>"), f"<builtin {path}>")
    try:
        text = p.read_text()
    except OSError as e:
        names = ", ".join(builtin_config_names())
        raise LightstageError(
            f"{p}: cannot read pipeline config ({e.strerror}; built-in configs: {names})"
        ) from None
    config = PipelineConfig.from_dict(_parse_yaml(text, str(p)), str(p))
    base = p.resolve().parent
    resolved = {
        k: os.fspath(base / v) if v is not None and not os.path.isabs(v) else v
        for k, v in (("capture", config.capture), ("work", config.work))
    }
    return dataclasses.replace(config, **resolved)


def _parse_yaml(text: str, source: str) -> Any:
    try:
        return yaml.safe_load(text)
    except yaml.YAMLError as e:
        raise LightstageError(f"{source}: invalid YAML: {e}") from None


def dump_yaml(data: dict[str, Any]) -> str:
    """The effective config as YAML in pipeline order."""
    return yaml.safe_dump(data, sort_keys=False, default_flow_style=False)
