"""Subcommands of the capture package: `stage` (presets, checks) and `capture` (validation)."""

from __future__ import annotations

import argparse
from pathlib import Path

from lightstage.cli_args import add_quiet


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
    register_capture(subparsers)


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


def register_capture(subparsers: argparse._SubParsersAction) -> None:
    """Add `capture validate`."""
    capture = subparsers.add_parser("capture", help="check a raw capture (frames, manifest)")
    capture_sub = capture.add_subparsers(dest="capture_command", metavar="ACTION", required=True)
    val = capture_sub.add_parser(
        "validate",
        help="scan every expected frame; write a manifest and a report (exit 0 only if all are usable)",
        description=(
            "Check every frame that stage.yaml and capture.yaml expect: presence, EXR header, truncation, "
            "resolution, channels (header-only, fast); with --deep also decode the pixels in separate "
            "processes and check for corrupt data, NaN/Inf and negative values. Writes manifest.json and "
            "report.json to CAPTURE/validation (or --out). Exit 0: every frame usable; 1: some are not; "
            "2: the capture itself is unusable (e.g. no stage.yaml)."
        ),
    )
    val.add_argument("capture", type=Path, metavar="CAPTURE", help="capture directory")
    val.add_argument("--deep", action="store_true", help="also decode pixels (slow; in worker processes)")
    val.add_argument("--workers", type=int, default=None, help="threads (header scan) / processes (--deep)")
    val.add_argument("--out", type=Path, default=None, help="output folder (default: CAPTURE/validation)")
    val.add_argument(
        "--timeout", type=float, default=None, help="seconds allowed to decode one file (--deep; default 300)"
    )
    add_quiet(val)
    val.set_defaults(func=_capture_validate)


def _capture_validate(args: argparse.Namespace) -> int:
    import sys

    from lightstage.capture.frame_checks import DEFAULT_TIMEOUT_S
    from lightstage.capture.validate import validate_capture
    from lightstage.errors import LightstageError

    if args.workers is not None and args.workers < 1:
        raise LightstageError(f"--workers: expected a positive integer, got {args.workers}")
    if args.timeout is not None and not args.timeout > 0:
        raise LightstageError(f"--timeout: expected a positive number, got {args.timeout}")
    result = validate_capture(
        args.capture,
        deep=args.deep,
        workers=args.workers,
        out_dir=args.out,
        progress=not args.quiet,
        timeout_s=args.timeout or DEFAULT_TIMEOUT_S,
    )
    out = args.out if args.out is not None else args.capture / "validation"
    print(result.summary(), file=sys.stdout if result.ok else sys.stderr)
    print(f"manifest: {out / 'manifest.json'}  report: {out / 'report.json'}")
    return 0 if result.ok else 1
