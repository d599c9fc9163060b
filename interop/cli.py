"""`lightstage export` and `lightstage import`: other tools' formats out of and into a work directory."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from lightstage.cli_args import add_quiet

IMPORT_FORMATS = ("olat", "openillumination")


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add `export` and `import`."""
    p = subparsers.add_parser(
        "export",
        help="write a work directory's data in another tool's format (olat, nerfstudio, colmap)",
        description="olat: the per-frame point-light format of NeRF / Gaussian-splatting relighting codes "
        "(transforms_{train,test}.json, one frame per (view, light), EXR + mask); nerfstudio: transforms.json "
        "with masks and the split's file lists; colmap: the calibrate stage's model with its images. "
        "Fields and conventions: docs/interop.md.",
    )
    p.add_argument("work", type=Path, help="work directory (after split; olat needs the processed frames)")
    p.add_argument("--format", required=True, choices=("olat", "nerfstudio", "colmap"), help="output format")
    p.add_argument("--out", required=True, type=Path, help="output folder (outside WORK)")
    add_quiet(p)
    p.set_defaults(func=_export)

    q = subparsers.add_parser(
        "import",
        help="make a work directory from a public OLAT dataset (olat, openillumination)",
        description="Write WORK's processed frames, masks, calibration, lights and split from FORMAT at PATH, "
        "so `lightstage run WORK/import.yaml --from split` trains and evaluates on it. olat: a folder with "
        "transforms_train.json and transforms_test.json; openillumination: an object folder (OLAT/obj_NN_name) "
        "with output/ and Lights/, and the dataset's light_pos.npy.",
    )
    q.add_argument("format", choices=IMPORT_FORMATS, help="dataset format")
    q.add_argument("path", type=Path, help="the dataset (folder)")
    q.add_argument("--work", required=True, type=Path, help="new work directory to write")
    q.add_argument("--lights", type=Path, help="openillumination: light_pos.npy (default: found beside PATH)")
    q.add_argument("--downscale", type=int, default=1, help="area-downscale the images by this integer")
    add_quiet(q)
    q.set_defaults(func=_import)


def _export(args: argparse.Namespace) -> int:
    from lightstage.interop.exports import export_work
    from lightstage.workdir import WorkDir

    summary = export_work(WorkDir.at(args.work), args.format, args.out, progress=not args.quiet)
    print(json.dumps(summary, indent=2))
    return 0


def _import(args: argparse.Namespace) -> int:
    from lightstage.errors import LightstageError
    from lightstage.interop.ingest import write_work
    from lightstage.workdir import WorkDir

    if args.format == "olat":
        from lightstage.interop.olat import read_olat

        if args.lights is not None:
            raise LightstageError("--lights: only for openillumination (olat frames carry pl_pos)")
        dataset = read_olat(args.path)
    else:
        from lightstage.interop.openillumination import read_openillumination

        dataset = read_openillumination(args.path, args.lights)
    summary = write_work(dataset, WorkDir.at(args.work), args.downscale, progress=not args.quiet)
    print(json.dumps({k: summary[k] for k in ("format", "frames", "views", "counts", "next")}, indent=2))
    return 0
