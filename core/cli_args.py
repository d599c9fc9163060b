"""The command-line conventions every subcommand shares: one help layout that shows defaults, one flag to be
quiet (`-q/--quiet`), one `--device` wording. Stage `cli` modules use these; pipelines/cli.py applies the
layout to the whole command tree."""

from __future__ import annotations

import argparse

DEVICE_HELP = "torch device: auto (CUDA when available, else CPU), cpu, cuda or cuda:N"


class HelpFormatter(argparse.RawDescriptionHelpFormatter):
    """Keeps descriptions as written and appends each option's default, unless its help already states one."""

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ""
        if "default" in text.lower() or action.default in (None, False, argparse.SUPPRESS, [], ()):
            return text
        if action.option_strings or action.nargs in (argparse.OPTIONAL, argparse.ZERO_OR_MORE):
            return f"{text} (default: %(default)s)"
        return text


def add_quiet(parser: argparse.ArgumentParser) -> None:
    """`-q/--quiet`: no progress bars (the one quiet flag of every command); read as `args.quiet`."""
    parser.add_argument("-q", "--quiet", action="store_true", help="no progress bars")


def add_device(parser: argparse.ArgumentParser, default: str = "auto") -> None:
    """`--device` with the one wording every command uses; read as `args.device`."""
    parser.add_argument("--device", default=default, help=DEVICE_HELP)


def apply_conventions(parser: argparse.ArgumentParser) -> None:
    """Give every parser of the tree the shared help layout, and each subcommand a description (its one-line
    help when it has no longer one), so `lightstage CMD --help` always says what CMD does."""
    parser.formatter_class = HelpFormatter
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            helps = {a.dest: a.help for a in action._choices_actions}
            for name, sub in action.choices.items():
                if not sub.description:
                    sub.description = helps.get(name)
                apply_conventions(sub)
