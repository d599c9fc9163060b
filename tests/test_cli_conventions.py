"""One CLI convention: every subcommand says what it does and shows its defaults, one quiet flag, one --device."""

from __future__ import annotations

import argparse

import pytest

from lightstage.cli_args import DEVICE_HELP, HelpFormatter
from lightstage.pipelines.cli import build_parser


def commands(
    parser: argparse.ArgumentParser, prefix: str = "lightstage"
) -> list[tuple[str, argparse.ArgumentParser]]:
    """(name, parser) of every subcommand of the tree, depth first."""
    out = []
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                out.append((f"{prefix} {name}", sub))
                out += commands(sub, f"{prefix} {name}")
    return out


COMMANDS = commands(build_parser())


def test_the_tree_is_walked():
    names = {n for n, _ in COMMANDS}
    assert {"lightstage run", "lightstage train", "lightstage preprocess", "lightstage stage check"} <= names


@pytest.mark.parametrize("name, parser", COMMANDS, ids=[n for n, _ in COMMANDS])
def test_each_command_describes_itself_and_shows_defaults(name, parser):
    assert parser.description and parser.description.strip(), f"{name}: no description"
    assert parser.formatter_class is HelpFormatter
    text = parser.format_help()
    for action in parser._actions:
        if not action.option_strings or action.help == argparse.SUPPRESS:
            continue
        opts = "/".join(action.option_strings)
        assert "--no-progress" not in action.option_strings, f"{name} {opts}: the quiet flag is --quiet"
        if "--device" in action.option_strings:
            assert action.help == DEVICE_HELP, f"{name} --device: use lightstage.cli_args.add_device"
        if action.default not in (None, False, argparse.SUPPRESS, [], ()):
            assert "default" in HelpFormatter(name)._get_help_string(action).lower(), f"{name} {opts}"
    assert "usage:" in text


def test_quiet_is_one_flag_everywhere():
    quiet = [n for n, p in COMMANDS if any("--quiet" in a.option_strings for a in p._actions)]
    assert {"lightstage run", "lightstage demo", "lightstage preprocess", "lightstage train"} <= set(quiet)
    for _, p in COMMANDS:
        for a in p._actions:
            if "--quiet" in a.option_strings:
                assert a.option_strings == ["-q", "--quiet"] and a.dest == "quiet"
