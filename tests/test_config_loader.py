"""The strict config loader (`lightstage.config`) and the up-front validation of a whole pipeline config:
unknown keys with the closest known key suggested, wrong types with the expected type, dataclass value checks as
one line, nested dataclasses, every section of the pipeline config, stage.yaml and capture.yaml, and
`lightstage run ... --to validate` failing before anything is written when a later section has a typo."""

from __future__ import annotations

import enum
import pickle
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Literal

import pytest
import yaml

from lightstage.capture.layout import CaptureInfo, save_capture_info
from lightstage.capture.presets import stage_preset
from lightstage.config import ConfigError, UnknownKeyError, load, require, suggest
from lightstage.errors import LightstageError
from lightstage.pipelines.cli import main as cli_main
from lightstage.pipelines.config import (
    PipelineConfig,
    builtin_config_names,
    load_pipeline_config,
    validate_pipeline_config,
)
from lightstage.pipelines.stages import STAGE_ORDER
from lightstage.training.config import BUILTIN_CONFIGS, load_config


class Colour(enum.Enum):
    RED = "red"
    BLUE = "blue"


@dataclass
class Inner:
    lr: float = 1e-3
    steps: int = 10
    mode: Literal["fast", "slow"] = "fast"

    def __post_init__(self) -> None:
        require(self.lr > 0, "lr", f"must be > 0, got {self.lr:g}")


@dataclass(frozen=True)
class Outer:
    name: str
    inner: Inner = field(default_factory=Inner)
    size: tuple[int, int] = (1, 2)
    tags: list[str] = field(default_factory=list)
    folder: Path | None = None
    colour: Colour = Colour.RED
    limit: float | None = None
    notes: dict[str, int] = field(default_factory=dict)


def error_of(data: object, cls: type = Outer, source: str | None = "c.yaml") -> str:
    with pytest.raises(ConfigError) as e:
        load(cls, data, source)
    assert isinstance(e.value, LightstageError) and "\n" not in str(e.value)
    return str(e.value)


# ---- the loader ------------------------------------------------------------------------------------------
def test_nested_dataclasses_and_types_convert() -> None:
    cfg = load(
        Outer,
        {
            "name": "a",
            "inner": {"lr": 2, "mode": "slow"},  # an int is a float
            "size": [3, 4],
            "tags": ["x"],
            "folder": "out/dir",
            "colour": "blue",
            "notes": {"k": 1},
        },
    )
    assert cfg == Outer(
        "a", Inner(2.0, 10, "slow"), (3, 4), ["x"], Path("out/dir"), Colour.BLUE, None, {"k": 1}
    )
    assert isinstance(cfg.inner.lr, float) and isinstance(cfg.size, tuple)
    assert load(Outer, {"name": "b", "inner": None}).inner == Inner()  # an empty YAML section: the defaults


def test_unknown_keys_suggest_the_closest_known_key() -> None:
    assert error_of({"name": "a", "inner": {"lrr": 1}}) == (
        "c.yaml: unknown key 'inner.lrr' (did you mean 'inner.lr'?)"
    )
    assert error_of({"nmae": "a"}) == "c.yaml: unknown key 'nmae' (did you mean 'name'?)"
    assert "(known: name, inner, size, tags, folder, colour, limit, notes)" in error_of({"zzz": 1})
    assert suggest("sphere_radus", ["sphere_radius", "saturation"]) == "sphere_radius"
    assert suggest("T", ["R", "t"]) == "t" and suggest("qqq", ["lr"]) is None


@pytest.mark.parametrize(
    "data, message",
    [
        ({"name": 3}, "c.yaml: name: expected a string, got 3"),
        ({"name": "a", "inner": {"steps": True}}, "inner.steps: expected an integer, got True"),
        ({"name": "a", "inner": {"steps": 2.5}}, "inner.steps: expected an integer, got 2.5"),
        ({"name": "a", "inner": {"lr": "fast"}}, "inner.lr: expected a number, got 'fast'"),
        ({"name": "a", "inner": {"lr": "1e-3"}}, "YAML reads 1e-3 as text: write 1.0e-3"),
        ({"name": "a", "inner": {"lr": False}}, "inner.lr: expected a number, got False"),
        (
            {"name": "a", "inner": {"mode": "fats"}},
            "expected one of 'fast', 'slow', got 'fats' (did you mean 'fast'?)",
        ),
        ({"name": "a", "size": [1]}, "size: expected a list of 2 items, got 1 item(s)"),
        ({"name": "a", "size": [1, "2"]}, "size[1]: expected an integer, got '2'"),
        ({"name": "a", "tags": "x"}, "tags: expected a list, got 'x'"),
        ({"name": "a", "folder": 7}, "folder: expected a path (string) or null, got 7"),
        ({"name": "a", "colour": "green"}, "colour: expected one of 'red', 'blue', got 'green'"),
        ({"name": "a", "limit": "none"}, "limit: expected a number or null, got 'none'"),
        ({"name": "a", "notes": {"k": "v"}}, "notes.k: expected an integer, got 'v'"),
        ({"name": "a", "inner": [1]}, "inner: expected a mapping, got [1]"),
        ({}, "c.yaml: name: missing (required)"),
        ([1, 2], "c.yaml: expected a mapping, got [1, 2]"),
    ],
)
def test_wrong_types_name_the_key_and_the_expected_type(data: object, message: str) -> None:
    assert message in error_of(data)


def test_value_checks_are_one_line_with_the_key() -> None:
    assert error_of({"name": "a", "inner": {"lr": -1}}) == "c.yaml: inner.lr: must be > 0, got -1"
    with pytest.raises(ConfigError, match="^lr: must be > 0"):
        Inner(lr=0.0)  # direct construction checks too


def test_errors_travel_and_nest() -> None:
    err = UnknownKeyError(("optim", "lrr"), ["lr", "steps"])
    placed = err.within("p.yaml", ("train",))
    assert str(placed) == "p.yaml: unknown key 'train.optim.lrr' (did you mean 'train.optim.lr'?)"
    assert str(pickle.loads(pickle.dumps(placed))) == str(placed)  # across dask / process pools
    assert str(err) == "unknown key 'optim.lrr' (did you mean 'optim.lr'?)"  # the original is unchanged
    own = ConfigError("must be > 0", "optim.lr", "base.yaml")
    assert own.within("p.yaml", "train") is own  # an error naming its own file keeps it


# ---- the stage configs as shipped --------------------------------------------------------------------------
def test_shipped_configs_load() -> None:
    for name in BUILTIN_CONFIGS:
        load_config(name)
    folder = resources.files("lightstage.training") / "configs"
    assert sorted(p.name[:-5] for p in folder.iterdir() if p.name.endswith(".yaml")) == sorted(
        BUILTIN_CONFIGS
    )
    for name in builtin_config_names():
        config = load_pipeline_config(name)
        validate_pipeline_config(config, None)
        config.effective()


def test_train_value_checks() -> None:
    for bad, message in (
        ({"optim": {"lr": -1}}, "optim.lr: must be > 0, got -1"),
        ({"optim": {"beta2": 1}}, "optim.beta2: must be in [0, 1), got 1"),
        (
            {"model": {"field": "hashgird"}},
            "model.field: expected one of 'mlp', 'hashgrid', got 'hashgird' (did you mean 'hashgrid'?)",
        ),
    ):
        with pytest.raises(ConfigError) as e:
            load_config("tiny", bad)
        assert str(e.value) == message  # the override's key, no file (the caller's file is added by it)
    with pytest.raises(ConfigError, match=r"^unknown key 'optim\.lrr' \(did you mean 'optim\.lr'\?\)$"):
        load_config("tiny", {"optim": {"lrr": 1}})


# ---- every section of the pipeline config, validated up front -----------------------------------------------
# (section, a misspelt key, the key the error must suggest): each stage's own config class and the pipeline's
SECTION_TYPOS = [
    ("validate", {"deeep": True}, "validate.deep"),
    ("preprocess", {"flare_treshold": 0.1}, "preprocess.flare_threshold"),
    ("calibrate", {"metod": "nominal"}, "calibrate.method"),
    ("split", {"protocl": "paper"}, "split.protocol"),
    ("split", {"protocol": {"lites": {"train": "rest"}}}, "split.protocol.lights"),
    ("bounds", {"resolutoin": 32}, "bounds.resolution"),
    ("shard", {"rays_per_shrd": 4096}, "shard.rays_per_shard"),
    ("train", {"optim": {"lrr": 0.01}}, "train.optim.lr"),
    ("train", {"config": "tiny", "model": {"mlp": {"widht": 8}}}, "train.model.mlp.width"),
    ("eval", {"chunck": 512}, "eval.chunk"),
    ("cluster", {"workres": 2}, "cluster.workers"),
    ("launch", {"launchr": "local"}, "launch.launcher"),
    ("demo", {"presett": "tiny"}, "demo.preset"),
    ("entry_points", {"trian": "x:y"}, "entry_points.train"),
]


def test_the_typo_table_covers_every_section() -> None:
    sections = {s for s, _, _ in SECTION_TYPOS}
    assert sections >= set(STAGE_ORDER) | {"cluster", "launch", "demo", "entry_points"}


def _unknown(expected: str) -> str:
    """The message for a misspelt key whose closest known key is `expected`."""
    return f"(did you mean '{expected}'?)"


@pytest.mark.parametrize("section, body, expected", SECTION_TYPOS, ids=[e for _, _, e in SECTION_TYPOS])
def test_unknown_key_in_every_section_is_caught_up_front(section: str, body: dict, expected: str) -> None:
    with pytest.raises(LightstageError) as e:
        validate_pipeline_config(PipelineConfig.from_dict({section: body}, "p.yaml"), None)
    message = str(e.value)
    assert message.startswith("p.yaml: unknown key '") and message.endswith(_unknown(expected)), message


def test_wrong_type_and_value_in_a_section_name_file_and_key() -> None:
    for data, message in (
        ({"shard": {"seed": "one"}}, "p.yaml: shard.seed: expected an integer, got 'one'"),
        ({"train": {"optim": {"lr": -1}}}, "p.yaml: train.optim.lr: must be > 0, got -1"),
        ({"train": {"config": "tiny", "optim": {"lr": -1}}}, "p.yaml: train.optim.lr: must be > 0, got -1"),
        (
            {"validate": {"max_bad_fraction": 2}},
            "p.yaml: validate.max_bad_fraction: expected a value in [0, 1]",
        ),
        ({"split": {"protocol": {"base": "papr"}}}, "p.yaml: split.protocol.base: expected one of paper"),
        ({"launch": {"nproc_per_node": 0}}, "p.yaml: launch.nproc_per_node: expected an integer >= 1, got 0"),
        ({"cluster": {"workers": -1}}, "p.yaml: cluster.workers: expected an integer >= 0, got -1"),
    ):
        with pytest.raises(LightstageError) as e:
            validate_pipeline_config(PipelineConfig.from_dict(data, "p.yaml"), None)
        assert str(e.value).startswith(message), (str(e.value), message)


def make_capture(root: Path, stage_yaml_extra: dict | None = None, capture_yaml: str | None = None) -> Path:
    """A capture folder with a valid stage.yaml and capture.yaml (no frames: nothing here gets that far)."""
    root.mkdir(parents=True)
    data = stage_preset("paper").to_dict()
    data.update(stage_yaml_extra or {})
    (root / "stage.yaml").write_text(yaml.safe_dump(data, sort_keys=False))
    if capture_yaml is None:
        save_capture_info(CaptureInfo(), root / "capture.yaml")
    else:
        (root / "capture.yaml").write_text(capture_yaml)
    return root


def test_stage_and_capture_yaml_are_validated_up_front(tmp_path: Path) -> None:
    config = PipelineConfig.from_dict({}, "p.yaml")
    validate_pipeline_config(config, make_capture(tmp_path / "ok"))
    bad_stage = make_capture(tmp_path / "a", {"sphere_radus": 1.5})
    with pytest.raises(LightstageError) as e:
        validate_pipeline_config(config, bad_stage)
    assert (
        str(e.value)
        == f"{bad_stage / 'stage.yaml'}: unknown key 'sphere_radus' (did you mean 'sphere_radius'?)"
    )
    bad_info = make_capture(tmp_path / "b", capture_yaml="path_templat: x\n")
    with pytest.raises(
        LightstageError, match=r"capture\.yaml: unknown key 'path_templat' \(did you mean 'path_template'"
    ):
        validate_pipeline_config(config, bad_info)


def written(work: Path) -> list[str]:
    """What a command left in WORK besides the work lock the CLI holds while it runs (lightstage.worklock)."""
    return sorted(p.name for p in work.iterdir() if p.name != ".lock") if work.exists() else []


def run_cli(argv: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str]:
    code = cli_main(argv)
    return code, capsys.readouterr().err


def test_run_to_validate_fails_before_anything_is_written(tmp_path: Path, capsys) -> None:
    capture = make_capture(tmp_path / "capture")
    work = tmp_path / "work"
    config = tmp_path / "p.yaml"
    config.write_text("cluster: {workers: 0}\ntrain:\n  config: tiny\n  optim: {lrr: 0.01}\n")
    code, err = run_cli(
        ["run", str(capture), "--work", str(work), "--config", str(config), "--to", "validate"], capsys
    )
    assert code == 2 and written(work) == []
    assert (
        err
        == f"lightstage: error: {config}: unknown key 'train.optim.lrr' (did you mean 'train.optim.lr'?)\n"
    )

    config.write_text("cluster: {workers: 0}\ntrain:\n  optim: {lr: -1}\n")
    code, err = run_cli(
        ["run", str(capture), "--work", str(work), "--config", str(config), "--to", "validate"], capsys
    )
    assert (code, err) == (2, f"lightstage: error: {config}: train.optim.lr: must be > 0, got -1\n")
    assert written(work) == []

    typo = make_capture(tmp_path / "typo", {"sphere_radus": 1.5})
    code, err = run_cli(["run", str(typo), "--work", str(work), "--workers", "0", "--to", "validate"], capsys)
    assert (
        code == 2 and written(work) == [] and err.count("\n") == 1 and "did you mean 'sphere_radius'?" in err
    )


def test_run_to_validate_with_a_clean_config_runs(tmp_path: Path, tiny_capture: Path, capsys) -> None:
    """The control: the same command without the typo runs the validate stage."""
    work = tmp_path / "work"
    config = tmp_path / "p.yaml"
    config.write_text("cluster: {workers: 0}\ntrain:\n  config: tiny\n  optim: {lr: 0.01}\n")
    argv = ["run", str(tiny_capture), "--work", str(work), "--config", str(config), "--to", "validate"]
    assert cli_main([*argv, "--quiet"]) == 0
    assert (work / "manifest.json").is_file()
