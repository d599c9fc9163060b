"""Subcommands of this package (`train`, `eval`); each handler imports its heavy dependencies lazily."""

from __future__ import annotations

import argparse


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add `lightstage train` and `lightstage eval`."""
    p = subparsers.add_parser(
        "train", help="train the relighting model from WORK/shards (resumes WORK/train)"
    )
    p.add_argument("work", help="work directory")
    p.add_argument(
        "--config",
        default="paper",
        help="paper | paper-lite | fast | cpu | tiny | a YAML file (default: paper)",
    )
    p.add_argument("--steps", type=int, default=None, help="total optimiser steps (overrides the config)")
    p.add_argument("--device", default="auto", help="cpu | cuda | auto (default)")
    p.add_argument(
        "--stop-at",
        type=int,
        default=None,
        help="end this run at this step with a checkpoint; rerun to continue (splits time-limited jobs)",
    )
    p.add_argument(
        "--eval-every", type=int, default=None, help="steps between test-PSNR previews (overrides the config)"
    )
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=_train)

    e = subparsers.add_parser("eval", help="score the trained model on the test split (reports/eval.json)")
    e.add_argument("work", help="work directory")
    e.add_argument("--checkpoint", default=None, help="checkpoint file (default: WORK/train/checkpoint.pt)")
    e.add_argument("--device", default="auto", help="cpu | cuda | auto (default)")
    e.add_argument("--max-images", type=int, default=None, help="score only the first N test images")
    e.add_argument(
        "--lpips-weights",
        default=None,
        help="local torchvision VGG16 state dict (.pth); none: LPIPS unavailable",
    )
    e.add_argument(
        "--lpips-linear-weights",
        default=None,
        help="LPIPS linear layers (.pth; default: the ones shipped in the lpips package)",
    )
    e.add_argument("--no-progress", action="store_true", help="no progress bar")
    e.set_defaults(func=_eval)


def _train(args: argparse.Namespace) -> int:
    import json

    from lightstage.errors import LightstageError
    from lightstage.training.config import load_config
    from lightstage.training.run import run_train
    from lightstage.workdir import WorkDir

    overrides: dict = {}
    for flag, value, least in (
        ("--steps", args.steps, 1),
        ("--stop-at", args.stop_at, 1),
        ("--eval-every", args.eval_every, 0),
    ):
        if value is not None and value < least:
            raise LightstageError(f"{flag} must be >= {least}")
    if args.steps is not None:
        overrides["optim"] = {"steps": args.steps}
    if args.eval_every is not None:
        overrides["eval"] = {"every": args.eval_every}
    config = load_config(args.config, overrides or None)
    summary = run_train(
        WorkDir.at(args.work),
        config,
        progress=not args.no_progress,
        device=args.device,
        stop_at=args.stop_at,
    )
    print(json.dumps(summary))
    return 0


def _eval(args: argparse.Namespace) -> int:
    import dataclasses
    import json

    from lightstage.training.evaluate import run_eval
    from lightstage.training.run import pick_device
    from lightstage.training.trained import load_trained
    from lightstage.workdir import WorkDir

    work = WorkDir.at(args.work)
    device = pick_device(args.device)
    cfg = load_trained(work, args.checkpoint, "cpu").config.eval
    changes = {
        k: v
        for k, v in (
            ("max_images", args.max_images),
            ("lpips_weights", args.lpips_weights),
            ("lpips_linear_weights", args.lpips_linear_weights),
        )
        if v is not None
    }
    summary = run_eval(
        work,
        dataclasses.replace(cfg, **changes),
        progress=not args.no_progress,
        checkpoint=args.checkpoint,
        device=str(device),
    )
    print(json.dumps(summary))
    return 0
