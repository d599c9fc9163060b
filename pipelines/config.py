"""The pipeline config: one YAML file with the capture, the work directory, how to execute (dask cluster,
training launcher) and every stage's parameters. Every part is read by the strict loader (`lightstage.config`):
each stage section by that stage's own config class, so messages name the file and the dotted key
(`p.yaml: unknown key 'train.optim.lrr' (did you mean 'train.optim.lr'?)`). `validate_pipeline_config` checks
every section and the capture's stage.yaml and capture.yaml before a run starts; `lightstage config show`
prints the effective config.
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

from lightstage.capture.layout import open_capture
from lightstage.config import ConfigError, UnknownKeyError, check_keys, load, parse_yaml, require
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

    def __post_init__(self) -> None:
        require(
            self.launcher in LAUNCHERS,
            "launcher",
            f"expected one of {', '.join(LAUNCHERS)}, got {self.launcher!r}",
        )
        require(
            self.nproc_per_node >= 1, "nproc_per_node", f"expected an integer >= 1, got {self.nproc_per_node}"
        )


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

    def __post_init__(self) -> None:
        require(
            self.cluster.workers >= 0,
            "cluster.workers",
            f"expected an integer >= 0, got {self.cluster.workers}",
        )
        require(
            self.cluster.threads_per_worker >= 1,
            "cluster.threads_per_worker",
            f"expected an integer >= 1, got {self.cluster.threads_per_worker}",
        )

    @classmethod
    def from_dict(cls, data: Any, source: str = "<config>") -> PipelineConfig:
        """Read a parsed pipeline config with the strict loader (top-level keys, cluster, launch, demo,
        entry_points); stage sections stay mappings, checked by `stage_config`. Errors name the file and key."""
        if data is None:
            data = {}
        if not isinstance(data, dict):
            raise ConfigError("expected a mapping at the top level", (), source)
        check_keys(data, TOP_KEYS, (), source)
        own = {
            k: os.fspath(v) if isinstance(v, os.PathLike) else v
            for k, v in data.items()
            if k not in STAGE_ORDER
        }
        top = load(cls, own, source)  # TOP_KEYS keeps `stages` and `source` out of the file
        for key in top.entry_points:
            if key not in STAGE_ORDER:
                raise UnknownKeyError(("entry_points", key), STAGE_ORDER, source)
        stages: dict[str, dict[str, Any]] = {}
        for name in STAGE_ORDER:
            section = data.get(name)
            if section is not None and not isinstance(section, dict):
                raise ConfigError(f"expected a mapping of parameters, got {section!r}", name, source)
            stages[name] = dict(section or {})
        return dataclasses.replace(top, stages=stages, source=source)

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
        """The stage's typed config from its section; errors name this file and the section's key."""
        impl = impl or self.stage_impl(name)
        try:
            return impl.make_config(self.stages.get(name, {}))
        except ConfigError as e:
            raise e.within(self.source, (name,)) from None
        except LightstageError as e:  # a stage's own (non-loader) message
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


def validate_pipeline_config(config: PipelineConfig, capture: str | os.PathLike[str] | None) -> None:
    """Check the whole run before its first stage starts: every stage section with that stage's config
    class (not only the selected stages), and the capture's stage.yaml and capture.yaml. Raises one
    LightstageError line naming the file and the key; writes nothing."""
    for name in STAGE_ORDER:
        config.stage_config(name)
    if capture is not None and "validate" not in config.entry_points:  # the capture format is validate's
        open_capture(capture)


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
        return PipelineConfig.from_dict(parse_yaml(text, f"<builtin {path}>"), f"<builtin {path}>")
    try:
        text = p.read_text()
    except OSError as e:
        names = ", ".join(builtin_config_names())
        raise LightstageError(
            f"{p}: cannot read pipeline config ({e.strerror}; built-in configs: {names})"
        ) from None
    config = PipelineConfig.from_dict(parse_yaml(text, str(p)), str(p))
    base = p.resolve().parent
    resolved = {
        k: os.fspath(base / v) if v is not None and not os.path.isabs(v) else v
        for k, v in (("capture", config.capture), ("work", config.work))
    }
    return dataclasses.replace(config, **resolved)


def dump_yaml(data: dict[str, Any]) -> str:
    """The effective config as YAML in pipeline order."""
    return yaml.safe_dump(data, sort_keys=False, default_flow_style=False)
