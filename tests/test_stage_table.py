"""The explicit stage table: every stage resolves to the function it names, inputs only point backwards, and
a broken stage module fails loudly with its own name (never "stage not available")."""

from __future__ import annotations

import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from lightstage.errors import LightstageError
from lightstage.pipelines.commands import STAGES as CLI_STAGES
from lightstage.pipelines.stages import CAPTURE, SPECS, STAGE_ORDER, resolve_stage, upstream
from lightstage.workdir import WorkDir


def test_every_stage_resolves_to_its_table_row() -> None:
    assert STAGE_ORDER == ("validate", "preprocess", "calibrate", "split", "bounds", "shard", "train", "eval")
    assert CLI_STAGES == STAGE_ORDER  # the CLI's --from/--only/--to choices
    for name in STAGE_ORDER:
        impl = resolve_stage(name)
        spec = SPECS[name]
        assert impl.run is spec.run and impl.config_cls is spec.config_cls
        assert impl.where == f"{spec.run.__module__}:run_{name}"
        config = impl.make_config({})
        assert config is None if name == "eval" else isinstance(config, spec.config_cls)
    assert resolve_stage("train").make_config({"config": "tiny"}).optim.steps > 0  # a named base config


def test_inputs_point_backwards_and_bounds_is_its_own_stage() -> None:
    for i, name in enumerate(STAGE_ORDER):
        for inp in SPECS[name].inputs:
            assert inp == CAPTURE or STAGE_ORDER.index(inp) < i, (name, inp)
    assert "bounds" in SPECS["shard"].inputs
    assert upstream("shard") == ["validate", "preprocess", "calibrate", "split", "bounds"]
    assert upstream("split") == ["validate", "preprocess"]  # split reads no calibration
    work = WorkDir.at("/w")
    assert work.bounds in SPECS["bounds"].outputs(work) and work.bounds not in SPECS["shard"].outputs(work)


def test_bad_entry_point_names_the_module() -> None:
    with pytest.raises(LightstageError, match="entry_points.split: no module 'no_such_module'"):
        resolve_stage("split", "no_such_module:run_split")
    with pytest.raises(LightstageError, match="has no function 'run_nothing'"):
        resolve_stage("split", "lightstage.dataset.split:run_nothing")


def test_syntax_error_in_a_stage_module_names_the_module(tmp_path: Path) -> None:
    """A stage module that does not import makes the table's import fail with that module's file named."""
    broken = tmp_path / "split.py"
    broken.write_text("def run_split(work, config:\n    pass\n")
    script = textwrap.dedent(
        f"""
        import importlib.abc, importlib.util, sys

        class Broken(importlib.abc.MetaPathFinder):
            def find_spec(self, name, path, target=None):
                if name == "lightstage.dataset.split":
                    return importlib.util.spec_from_file_location(name, {str(broken)!r})
                return None

        sys.meta_path.insert(0, Broken())
        import lightstage.pipelines.stages
        """
    )
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120)
    assert proc.returncode != 0
    assert "SyntaxError" in proc.stderr and str(broken) in proc.stderr
    assert "not available" not in proc.stderr
