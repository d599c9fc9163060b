"""The `lightstage` command line: one subcommand per stage, registered by each package's `cli` module.

Each `cli` module exposes `register(subparsers)` and imports heavy libraries only inside its handlers,
so `lightstage --help` stays fast. Bad input ends in a one-line message and exit code 2, an environment
fault (disk full, permission denied) in one line and exit code 1 (`--debug` shows the traceback).

A command that writes into a work directory holds its lock while it runs (`lightstage.worklock`, taken here
and nowhere else): a second command on the same WORK is refused at once, naming the holder.
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import shlex
import sys
import traceback
from collections.abc import Iterator
from pathlib import Path

from lightstage import __version__
from lightstage.cli_args import apply_conventions
from lightstage.errors import LightstageError

# The packages that contribute subcommands, in the order of the pipeline.
COMMAND_MODULES = (
    "lightstage.capture.cli",
    "lightstage.simulator.cli",
    "lightstage.preprocess.cli",
    "lightstage.calibration.cli",
    "lightstage.dataset.cli",
    "lightstage.interop.cli",
    "lightstage.training.cli",
    "lightstage.viewer.cli",
    "lightstage.pipelines.commands",
)

EXIT_FAILED = 1
EXIT_BAD_INPUT = 2

# Subcommands that write into a work directory (argument `work`) and so hold its lock while they run; the
# value says whether the command may create WORK. A command whose WORK can come from elsewhere (run: the
# pipeline config) sets `resolve_work` in its parser defaults. Commands that only read a work directory take
# no lock, so they can run beside a training. tests/test_worklock.py checks that every subcommand with a
# `work` argument is in one of the two.
LOCKING_COMMANDS = {
    "run": True,
    "demo": True,
    "preprocess": True,
    "calibrate": False,
    "split": True,  # --stage-preset splits a built-in stage into a new WORK
    "bounds": False,
    "shard": False,
    "train": False,
    "eval": False,
    "import": True,  # writes a new WORK from an external dataset
}
READ_ONLY_COMMANDS = frozenset({"relight", "render", "mesh", "export", "view"})  # write --out / WORK/viewer


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
    apply_conventions(parser)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return EXIT_BAD_INPUT if args.command is None and argv is None and len(sys.argv) <= 1 else 0
    try:
        with _work_lock(args, sys.argv[1:] if argv is None else argv):
            return int(args.func(args) or 0)
    except LightstageError as e:
        if args.debug:
            traceback.print_exc()
        print(f"lightstage: error: {e}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except OSError as e:  # the environment (disk full, permissions, a vanished file), not the input
        if args.debug:
            traceback.print_exc()
        print(f"lightstage: error: {_os_error_line(e)}", file=sys.stderr)
        return EXIT_FAILED
    except KeyboardInterrupt:
        print("lightstage: interrupted (finished outputs are kept; rerun to resume)", file=sys.stderr)
        return 130


def work_of(args: argparse.Namespace) -> Path | None:
    """The work directory a locking command writes (None for other commands, or when none is given: the
    command itself then says so)."""
    if args.command not in LOCKING_COMMANDS:
        return None
    work = getattr(args, "work", None)
    resolve = getattr(args, "resolve_work", None)
    if work is None and resolve is not None:
        work = args.work = resolve(args)
    return Path(work) if work is not None else None


@contextlib.contextmanager
def _work_lock(args: argparse.Namespace, argv: list[str]) -> Iterator[None]:
    """Hold the lock of the command's work directory (if it writes one) around the command."""
    work = work_of(args)
    if work is None:
        yield
        return
    from lightstage.worklock import hold_work_lock

    command = "lightstage " + shlex.join(str(a) for a in argv)
    with hold_work_lock(work, command, create=LOCKING_COMMANDS[args.command]) as lock:
        if lock.removed:
            print(
                f"lightstage: note: removed {len(lock.removed)} temporary file(s) left in {work} by an "
                "interrupted run",
                file=sys.stderr,
            )
        yield


def _os_error_line(e: OSError) -> str:
    """'FILE: reason' for an OSError (its own text when it names no file)."""
    if e.filename is not None and e.strerror:
        return f"{e.filename}: {e.strerror}"
    return str(e) or type(e).__name__


if __name__ == "__main__":
    sys.exit(main())
