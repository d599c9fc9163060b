"""Subcommands of this package: `train`, `eval`, and those that use a trained model, `relight` (envmap),
`render` (novel views and lights), `mesh`. Each handler imports its heavy dependencies lazily."""

from __future__ import annotations

import argparse
import json

from lightstage.cli_args import add_device, add_quiet


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
    add_device(p)
    p.add_argument(
        "--stop-at",
        type=int,
        default=None,
        help="end this run at this step with a checkpoint; rerun to continue (splits time-limited jobs)",
    )
    p.add_argument(
        "--eval-every", type=int, default=None, help="steps between test-PSNR previews (overrides the config)"
    )
    add_quiet(p)
    p.set_defaults(func=_train)

    e = subparsers.add_parser("eval", help="score the trained model on the test split (reports/eval.json)")
    e.add_argument("work", help="work directory")
    e.add_argument("--checkpoint", default=None, help="checkpoint file (default: WORK/train/checkpoint.pt)")
    add_device(e)
    e.add_argument("--max-images", type=int, default=None, help="score only the first N test images")
    e.add_argument("--no-lpips", action="store_true", help="skip LPIPS (eval.lpips: false)")
    add_quiet(e)
    e.set_defaults(func=_eval)
    p = subparsers.add_parser(
        "relight",
        help="relight a trained model with a lat-long HDR environment map (median cut)",
        description="Relight a trained model with an envmap: median-cut lights (or every pixel), one OLAT "
        "query per light, summed per RGB channel. Writes EXR (linear HDR) + PNG previews and relight.json. "
        "Conventions: docs/relighting.md.",
    )
    p.add_argument("work", help="work directory")
    p.add_argument("--envmap", required=True, help="lat-long HDR map (.exr, .hdr, ...)")
    p.add_argument(
        "--lights",
        default="64",
        help="power of two, 'all', 'stage' (the viewer's interpolated stage-light basis), or a comma list, "
        "e.g. 16,64,all (default 64)",
    )
    p.add_argument(
        "--camera",
        action="append",
        default=[],
        help="camera spec (repeatable): GROUP/CAMERA, orbit[:az=,elev=,dist=,fov=,size=WxH], "
        "K=fx,fy,cx,cy;R=...;t=...;size=WxH, or FILE.json (default: the first calibrated view)",
    )
    p.add_argument("--resolution", default="32x16", help="envmap resampling WIDTHxHEIGHT (default 32x16)")
    p.add_argument("--rotate-deg", type=float, default=0.0, help="rotate the envmap about +z (degrees)")
    p.add_argument(
        "--rotate-sweep",
        type=int,
        default=0,
        metavar="N",
        help="also render N frames of one envmap turn about +z (first camera and light count) as an H.264 MP4",
    )
    _common(p)
    p.add_argument("--out", required=True, help="output folder")
    p.set_defaults(func=_relight)

    p = subparsers.add_parser(
        "render",
        help="render a trained model from any camera under any point light or direction",
        description="Render a trained model: camera = GROUP/CAMERA, orbit[:...], explicit K/R/t or FILE.json; "
        "light = dir:x,y,z, azel:AZ,ELEV, pos:x,y,z[,I] or GROUP/INDEX. --orbit N turns the camera about "
        "+z through the scene centre and writes an MP4 and a PNG strip.",
    )
    p.add_argument("work", help="work directory")
    p.add_argument("--camera", required=True, help="camera spec (see `lightstage relight --help`)")
    p.add_argument(
        "--light", required=True, help="light spec: dir:x,y,z | azel:AZ,ELEV | pos:x,y,z[,I] | GROUP/INDEX"
    )
    p.add_argument("--orbit", type=int, default=0, help="frames of a full orbit (writes orbit.mp4 + strip)")
    p.add_argument("--fps", type=float, default=24.0, help="video frame rate (default 24)")
    _common(p)
    p.add_argument("--out", required=True, help="output folder")
    p.set_defaults(func=_render)

    p = subparsers.add_parser(
        "mesh",
        help="extract a mesh (PLY, world units) from a trained model's density",
        description="Evaluate the density on an N^3 grid over the scene bounds (chunked, GPU when present), "
        "run marching cubes at a density level and write a binary PLY in world units (metres). The level is, by "
        "default, the median density where rays through the grid reach transmittance 1/2 (the field's "
        "median-depth surface, docs/relighting.md); --threshold gives it by hand.",
    )
    p.add_argument("work", help="work directory")
    p.add_argument("--resolution", type=int, default=256, help="grid points per axis (default 256)")
    p.add_argument(
        "--threshold",
        type=float,
        default=None,
        help="density level of the surface in the model's units (default: from the field's transmittance)",
    )
    p.add_argument("--chunk", type=int, default=262144, help="points per density query")
    p.add_argument("--checkpoint", default=None, help="checkpoint file (default: the latest)")
    add_device(p)
    p.add_argument("--out", required=True, help="output mesh, a .ply file (binary PLY)")
    p.set_defaults(func=_mesh)


def _train(args: argparse.Namespace) -> int:
    import json

    from lightstage.errors import LightstageError
    from lightstage.training.config import load_config
    from lightstage.training.train_stage import run_train
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
        progress=not args.quiet,
        device=args.device,
        stop_at=args.stop_at,
    )
    print(json.dumps(summary))
    return 0


def _eval(args: argparse.Namespace) -> int:
    import dataclasses
    import json

    from lightstage.training.evaluate import run_eval
    from lightstage.training.inference import load_trained
    from lightstage.training.train_stage import pick_device
    from lightstage.workdir import WorkDir

    work = WorkDir.at(args.work)
    device = pick_device(args.device)
    cfg = load_trained(work, args.checkpoint, "cpu").config.eval
    changes = {"max_images": args.max_images} if args.max_images is not None else {}
    if args.no_lpips:
        changes["lpips"] = False
    summary = run_eval(
        work,
        dataclasses.replace(cfg, **changes),
        progress=not args.quiet,
        checkpoint=args.checkpoint,
        device=str(device),
    )
    print(json.dumps(summary))
    return 0


def _common(p: argparse.ArgumentParser) -> None:
    p.add_argument("--downscale", type=int, default=1, help="render at 1/N of the camera's resolution")
    p.add_argument("--exposure", type=float, default=None, help="preview exposure (default: auto, 99th pct)")
    p.add_argument("--checkpoint", default=None, help="checkpoint file (default: the latest)")
    add_device(p, default="cpu")
    p.add_argument(
        "--light-distance",
        type=float,
        default=None,
        help="capture light distance d in metres (default: median calibrated light distance, else 1.5)",
    )
    p.add_argument(
        "--light-intensity", type=float, default=1.0, help="capture point-light intensity I (default 1)"
    )


def _work(args: argparse.Namespace):
    from lightstage.errors import LightstageError
    from lightstage.workdir import WorkDir

    work = WorkDir.at(args.work)
    if not work.root.is_dir():
        raise LightstageError(f"{work.root}: work directory not found")
    return work


def _relight(args: argparse.Namespace) -> int:
    from lightstage.training.relight import RelightConfig, run_relight

    config = RelightConfig(
        envmap=args.envmap,
        lights=args.lights,
        cameras=list(args.camera),
        resolution=args.resolution,
        rotate_deg=args.rotate_deg,
        rotate_sweep=args.rotate_sweep,
        downscale=args.downscale,
        exposure=args.exposure,
        checkpoint=args.checkpoint,
        device=args.device,
        light_distance=args.light_distance,
        light_intensity=args.light_intensity,
        out=args.out,
    )
    summary = run_relight(_work(args), config)
    _print(summary)
    return 0


def _render(args: argparse.Namespace) -> int:
    from lightstage.training.novel_views import RenderConfig, run_render

    config = RenderConfig(
        camera=args.camera,
        light=args.light,
        orbit=args.orbit,
        fps=args.fps,
        downscale=args.downscale,
        exposure=args.exposure,
        checkpoint=args.checkpoint,
        device=args.device,
        light_distance=args.light_distance,
        light_intensity=args.light_intensity,
        out=args.out,
    )
    _print(run_render(_work(args), config))
    return 0


def _mesh(args: argparse.Namespace) -> int:
    from lightstage.training.mesh import MeshConfig, run_mesh

    config = MeshConfig(
        resolution=args.resolution,
        threshold=args.threshold,
        chunk=args.chunk,
        checkpoint=args.checkpoint,
        device=args.device,
        out=args.out,
    )
    _print(run_mesh(_work(args), config))
    return 0


def _print(summary: dict) -> None:
    print(json.dumps(summary, indent=2, default=str))
