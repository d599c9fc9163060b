"""The `lightstage` command line: one subcommand per stage, registered by each package's `cli` module.

Each `cli` module exposes `register(subparsers)` and imports heavy libraries only inside its handlers,
so `lightstage --help` stays fast. Bad input ends in a one-line message and exit code 2 (`--debug` shows
the traceback).
"""

from __future__ import annotations

import argparse
import importlib
import sys
import traceback

from lightstage import __version__
from lightstage.errors import LightstageError

# The packages that contribute subcommands, in the order of the pipeline.
COMMAND_MODULES = (
    "lightstage.capture.cli",
    "lightstage.simulator.cli",
    "lightstage.preprocess.cli",
    "lightstage.calibration.cli",
    "lightstage.dataset.cli",
    "lightstage.training.cli",
    "lightstage.training.use_cli",
    "lightstage.pipelines.commands",
)

EXIT_BAD_INPUT = 2


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="lightstage",
        description="Raw light-stage OLAT captures to relightable neural models of translucent objects.",
    )
    parser.add_argument("--version", action="version", version=f"lightstage {__version__}")
    parser.add_argument("--debug", action="store_true", help="show full tracebacks on errors")
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in COMMAND_MODULES:
        importlib.import_module(name).register(subparsers)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return EXIT_BAD_INPUT if args.command is None and argv is None and len(sys.argv) <= 1 else 0
    try:
        return int(args.func(args) or 0)
    except LightstageError as e:
        if args.debug:
            traceback.print_exc()
        print(f"lightstage: error: {e}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except KeyboardInterrupt:
        print("lightstage: interrupted (finished outputs are kept; rerun to resume)", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
