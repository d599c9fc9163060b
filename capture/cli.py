"""Subcommands of the capture package: `stage` (presets, checks) and `capture` (validation)."""

from __future__ import annotations

import argparse
from pathlib import Path


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add `stage` and `capture` subcommands."""
    stage = subparsers.add_parser("stage", help="describe or check a light stage (stage.yaml)")
    stage_sub = stage.add_subparsers(dest="stage_command", metavar="ACTION", required=True)
    show = stage_sub.add_parser("preset", help="write a built-in stage preset as stage.yaml")
    show.add_argument("name", help="preset name (paper)")
    show.add_argument("--out", type=Path, help="file to write (default: print to stdout)")
    show.set_defaults(func=_stage_preset)
    check = stage_sub.add_parser("check", help="validate a stage.yaml and print its summary")
    check.add_argument("path", type=Path)
    check.set_defaults(func=_stage_check)


def _stage_preset(args: argparse.Namespace) -> int:
    import yaml

    from lightstage.capture.presets import stage_preset

    stage = stage_preset(args.name)
    if args.out:
        stage.save(args.out)
        print(f"wrote {args.out}")
    else:
        print(yaml.safe_dump(stage.to_dict(), sort_keys=False, default_flow_style=None), end="")
    return 0


def _stage_check(args: argparse.Namespace) -> int:
    from lightstage.capture.stage import load_stage

    stage = load_stage(args.path)
    print(
        f"{args.path}: stage {stage.name!r}: {len(stage.cameras)} cameras, {len(stage.lights)} lights, "
        f"{len(stage.groups)} groups, {stage.width}x{stage.height}, saturation {stage.saturation}, "
        f"{stage.num_frames} frames per capture"
    )
    return 0
