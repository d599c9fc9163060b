"""Subcommands of this package; each handler imports its heavy dependencies lazily."""

from __future__ import annotations

import argparse
from pathlib import Path

from lightstage.cli_args import add_quiet


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add the `simulate` subcommand."""
    p = subparsers.add_parser(
        "simulate",
        help="write a simulated raw capture with ground truth (demo data, test fixtures)",
        description="Simulate a light-stage OLAT capture of a translucent object: stage.yaml (nominal), "
        "capture.yaml, half EXR frames, a mirror-ball light probe (probe/), ground_truth/ and contact_sheet.png.",
    )
    p.add_argument("out", type=Path, help="output capture directory (must be absent or empty)")
    p.add_argument(
        "--preset",
        default="tiny",
        help="tiny | small | paper-512 (the paper's 59,580 frames at 512 x 344) | paper (needs all three selectors)",
    )
    p.add_argument("--seed", type=int, default=0, help="random seed (same seed, same bytes)")
    p.add_argument("--groups", help="group names or indices, e.g. 000,040 or 0-2")
    p.add_argument("--cameras", help="camera ids or indices, e.g. cam00,cam03 or 0-4")
    p.add_argument("--lights", help="light indices, e.g. 0,10,20-25 or 0-31:2 (every other)")
    p.add_argument("--workers", type=int, help="worker processes (default: available cores)")
    p.add_argument(
        "--realism",
        choices=("stage", "clean"),
        help="stage: a real stage's lit cloth backdrop, sensor noise and black level, 12-bit darks, unequal "
        "LEDs, dark-albedo patches; clean: the old dark, clean render (default: the preset's; small: stage)",
    )
    p.add_argument(
        "--case",
        action="append",
        dest="cases",
        metavar="NAME",
        help="a real capture's failure case, repeatable: grey-object, candle, speculars, srgb8, dark-cloth, "
        "soft-shadows, lit-floor, camera-side-lights (docs/simulator.md)",
    )
    p.add_argument("--no-probe", action="store_true", help="skip the mirror-ball light-probe frames (probe/)")
    add_quiet(p)
    p.set_defaults(func=_simulate)


def _simulate(args: argparse.Namespace) -> int:
    from lightstage.errors import LightstageError
    from lightstage.simulator.simulate import simulate_capture

    if args.workers is not None and args.workers < 1:
        raise LightstageError(f"--workers must be >= 1, got {args.workers}")
    simulate_capture(
        args.out,
        preset=args.preset,
        seed=args.seed,
        groups=args.groups,
        cameras=args.cameras,
        lights=args.lights,
        workers=args.workers,
        progress=not args.quiet,
        probe=not args.no_probe,
        realism=args.realism,
        cases=args.cases,
    )
    return 0
