"""Subcommands of the dataset package: `split`, `bounds`, `shard`; each handler imports heavy libraries lazily."""

from __future__ import annotations

import argparse
from pathlib import Path


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add `split`, `bounds` and `shard`."""
    p = subparsers.add_parser(
        "split", help="write the train/test split of a work directory as data (split.json)"
    )
    p.add_argument("work", type=Path, help="work directory")
    p.add_argument(
        "--protocol", default="paper", help="paper | synthetic | a protocol YAML file (default: paper)"
    )
    p.add_argument(
        "--stage-preset", default=None, help="split a built-in stage (e.g. paper) without any capture"
    )
    p.set_defaults(func=_split)

    b = subparsers.add_parser("bounds", help="estimate the scene bounds (visual hull) -> bounds.json")
    b.add_argument("work", type=Path, help="work directory")
    b.add_argument("--resolution", type=int, default=None, help="voxels per axis (default 64)")
    b.add_argument("--force", action="store_true", help="recompute even if bounds.json exists")
    b.set_defaults(func=_bounds)

    s = subparsers.add_parser("shard", help="write training ray shards and test images for the trainer")
    s.add_argument("work", type=Path, help="work directory")
    s.add_argument("--rays-per-shard", type=int, default=None, help="rays per shard (multiple of 8)")
    s.add_argument(
        "--rays-per-image", type=int, default=None, help="rays sampled per training image (multiple of 8)"
    )
    s.add_argument("--workers", type=int, default=None, help="local processes when no dask client is used")
    s.add_argument("--seed", type=int, default=None)
    s.add_argument("--force", action="store_true", help="rewrite the shards even if they are up to date")
    s.add_argument(
        "--verify", action="store_true", help="only verify existing shards against their checksums"
    )
    s.set_defaults(func=_shard)


def _split(args: argparse.Namespace) -> int:
    from lightstage.dataset.split import SplitConfig, run_split
    from lightstage.workdir import WorkDir

    cfg = SplitConfig(protocol=args.protocol, stage_preset=args.stage_preset)
    s = run_split(WorkDir.at(args.work), cfg)
    c = s["counts"]
    print(
        f"split {s['protocol']!r} on stage {s['stage_name']!r}: {c['train']} train / {c['test']} test images "
        f"({c['train_cameras']} train cameras x {c['train_lights']} train lights; {c['test_views']} test views x "
        f"{c['test_lights']} test lights; excluded {c['train_excluded']} train, {c['test_excluded']} test) "
        f"-> {s['output']}"
    )
    return 0


def _bounds(args: argparse.Namespace) -> int:
    from lightstage.dataset.bounds import BoundsConfig, run_bounds
    from lightstage.workdir import WorkDir

    d = {"force": args.force}
    if args.resolution:
        d["resolution"] = args.resolution
    s = run_bounds(WorkDir.at(args.work), BoundsConfig.from_dict(d))
    print(
        f"bounds: centre {[round(x, 4) for x in s['centre']]} m, scale {s['scale']:.4f} m "
        f"({s['views']} views, {s['occupied_voxels']} occupied voxels) -> {s['output']}"
    )
    return 0


def _shard(args: argparse.Namespace) -> int:
    from lightstage.dataset.shard_config import ShardConfig
    from lightstage.dataset.shards import run_shard, verify_shards
    from lightstage.workdir import WorkDir

    work = WorkDir.at(args.work)
    if args.verify:
        n = verify_shards(work.shards_dir)
        print(f"{n} shards verified against {work.shards_dir / 'manifest.json'}")
        return 0
    d: dict = {"force": True} if args.force else {}
    for key in ("rays_per_shard", "rays_per_image", "workers", "seed"):
        v = getattr(args, key)
        if v is not None:
            d[key] = v
    s = run_shard(work, ShardConfig.from_dict(d))
    print(
        f"shards: {s['rays']} rays in {s['shards']} shards ({s['bytes_per_ray']:.1f} bytes/ray on disk, "
        f"zones fg/band/bg {s['zone_counts']}), {s['test_images']} test images -> {s['output']}"
    )
    return 0
