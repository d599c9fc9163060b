"""`lightstage view WORK`: build the relighting viewer of a work directory (captured frames and/or a trained
model) and serve it on localhost, or write it to a folder with --export (docs/viewer.md)."""

from __future__ import annotations

import argparse

from lightstage.cli_args import add_device, add_quiet


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add `lightstage view`."""
    p = subparsers.add_parser(
        "view",
        help="interactive relighting viewer of WORK in the browser (serve on localhost or --export a folder)",
        description="Build a self-contained WebGL2 viewer of WORK: per view of a turntable ring, a compressed "
        "OLAT basis from the captured frames and/or a trained model's renders under dense stage lights; "
        "drag a point light, turn an envmap, change the exposure, A/B against the captured frame. Serves it "
        "on localhost (WORK/viewer, rebuilt only when its inputs or options change), or writes it to --export "
        "DIR. Docs: docs/viewer.md.",
    )
    p.add_argument("work", help="work directory")
    p.add_argument("--port", type=int, default=8023, help="localhost port to serve on (0: any free port)")
    p.add_argument("--export", default=None, metavar="DIR", help="write the viewer folder to DIR and exit")
    p.add_argument("--source", default="auto", help="capture | model | both | auto (what WORK has)")
    p.add_argument(
        "--camera", default=None, help="camera of the view ring (default: the median-elevation one)"
    )
    p.add_argument("--views", type=int, default=0, help="calibrated views in the ring (0: one per group)")
    p.add_argument("--novel", type=int, default=1, help="novel model views between consecutive ring views")
    p.add_argument("--basis-lights", type=int, default=64, help="stage lights of the model basis")
    p.add_argument(
        "--capture-lights",
        type=int,
        default=0,
        help="most captured lights per view (0: all; else a spread subset)",
    )
    p.add_argument(
        "--tolerance", type=float, default=0.03, help="relative error allowed in each view's compressed basis"
    )
    p.add_argument("--max-components", type=int, default=64, help="most basis components kept per view")
    p.add_argument(
        "--envmap",
        action="append",
        default=[],
        help="lat-long HDR map to offer (repeatable; a sky is built in)",
    )
    p.add_argument(
        "--display-size",
        type=int,
        default=512,
        help="longest side of the views in pixels (frames and renders area-downscaled; 0: as processed)",
    )
    p.add_argument(
        "--bundle-mb",
        type=float,
        default=300.0,
        help="bound of the bundle in MB: each view's basis components get a share of it",
    )
    p.add_argument("--envmap-resolution", default="32x16", help="envmap resampling WIDTHxHEIGHT")
    p.add_argument("--orbit-views", type=int, default=12, help="model views without a calibration (an orbit)")
    p.add_argument("--orbit-size", default="256x192", help="WIDTHxHEIGHT of those orbit views")
    p.add_argument("--checkpoint", default=None, help="checkpoint file (default: WORK/train/checkpoint.pt)")
    add_device(p)
    p.add_argument("--rebuild", action="store_true", help="rebuild WORK/viewer even when it is up to date")
    p.add_argument("--no-serve", action="store_true", help="build WORK/viewer and exit")
    add_quiet(p)
    p.set_defaults(func=_view)


def _view(args: argparse.Namespace) -> int:
    from pathlib import Path

    from lightstage.errors import LightstageError
    from lightstage.viewer.build import ViewerConfig, build_key, build_viewer, is_current
    from lightstage.workdir import WorkDir

    work = WorkDir.at(args.work)
    if not work.root.is_dir():
        raise LightstageError(f"{work.root}: work directory not found")
    device = args.device
    if device == "auto":
        import torch

        device = "cuda" if torch.cuda.is_available() else "cpu"
    config = ViewerConfig(
        source=args.source,
        camera=args.camera,
        views=args.views,
        novel=args.novel,
        basis_lights=args.basis_lights,
        capture_lights=args.capture_lights,
        tolerance=args.tolerance,
        max_components=args.max_components,
        envmaps=list(args.envmap),
        envmap_resolution=args.envmap_resolution,
        orbit_views=args.orbit_views,
        orbit_size=args.orbit_size,
        checkpoint=args.checkpoint,
        device=device,
        display_size=args.display_size,
        bundle_mb=args.bundle_mb,
    )
    for path in config.envmaps:
        if not Path(path).is_file():
            raise LightstageError(f"{path}: envmap file not found")
    bundle = Path(args.export) if args.export else work.root / "viewer"
    if not args.rebuild and config == ViewerConfig(device=device):
        config = _recorded_config(
            bundle, config
        )  # no build options given: keep the bundle's (e.g. the demo's)
    if args.rebuild or not is_current(bundle, build_key(work, config)):
        manifest = build_viewer(work, config, bundle, progress=not args.quiet)
        _summary(bundle, manifest)
    else:
        print(f"lightstage view: {bundle} is up to date (--rebuild to build it again)")
    if args.export or args.no_serve:
        return 0
    from lightstage.viewer.serve import serve

    serve(bundle, args.port)
    return 0


def _recorded_config(bundle, default):
    """The options an existing bundle was built with (its inputs are still checked), else `default`."""
    import json

    from lightstage.errors import LightstageError
    from lightstage.viewer.build import ViewerConfig

    try:
        recorded = json.loads((bundle / "manifest.json").read_text())["build"]["key"]["config"]
        return ViewerConfig.from_dict({**recorded, "device": default.device})
    except (OSError, ValueError, KeyError, TypeError, LightstageError):
        return default


def _summary(bundle, manifest) -> None:
    build = manifest["build"]
    sets = ", ".join(
        f"{s['source']} ({len(s['views'])} views, {s['basis_lights']} lights)" for s in manifest["sets"]
    )
    tolerance = build["key"]["config"]["tolerance"]
    over = sum(v["relative_error"] > tolerance for s in manifest["sets"] for v in s["views"])
    note = (
        f"; {over} view(s) above --tolerance {tolerance:g} (their components are capped by --bundle-mb or "
        "--max-components)"
        if over
        else ""
    )
    print(
        f"lightstage view: wrote {bundle}: {sets}; {build['bytes'] / 1e6:.1f} MB, built in "
        f"{build['wall_seconds']:.0f} s ({build['cpu_seconds']:.0f} CPU-s){note}"
    )
