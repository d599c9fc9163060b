"""Subcommands of this package; each handler imports its heavy dependencies lazily."""

from __future__ import annotations

import argparse
from pathlib import Path

from lightstage.cli_args import add_quiet


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add this package's subcommands."""
    p = subparsers.add_parser(
        "calibrate",
        help="camera poses, turntable axis/yaws and light positions of a work directory",
        description="Calibrate WORK: SfM (pycolmap) on the preprocess SfM images and masks, registered to the stage frame, or "
        "the nominal stage.yaml geometry. Writes WORK/calibration/ and WORK/reports/calibration.json.",
    )
    p.add_argument("work", type=Path, help="work directory (after `lightstage preprocess`)")
    p.add_argument("--method", choices=["sfm", "nominal"], default="sfm", help="sfm (default) or nominal")
    p.add_argument("--intrinsics", help="intrinsics JSON from `lightstage calibrate-intrinsics`")
    p.add_argument("--threads", type=int, default=2, help="pycolmap threads (default 2)")
    p.add_argument("--keep-sfm", action="store_true", help="keep WORK/calibration/sfm (images, database)")
    add_quiet(p)
    p.set_defaults(func=_calibrate)

    q = subparsers.add_parser(
        "calibrate-intrinsics",
        help="fit camera intrinsics + distortion from ChArUco board images",
        description="Fit K and OpenCV distortion per camera from BOARDS/<camera id>/*.png (OpenCV 5 "
        "CharucoDetector + calibrateCamera); write a JSON that `calibrate --intrinsics` reads.",
    )
    q.add_argument("boards", type=Path, help="folder with one sub-folder of board images per camera id")
    q.add_argument("out", type=Path, help="output JSON")
    q.add_argument("--squares", default="11x8", help="board squares XxY (default 11x8)")
    q.add_argument("--square-length", type=float, default=0.03, help="square side in metres")
    q.add_argument("--marker-length", type=float, default=0.022, help="marker side in metres")
    q.add_argument("--dictionary", default="DICT_5X5_100", help="ArUco dictionary (default DICT_5X5_100)")
    q.set_defaults(func=_calibrate_intrinsics)


def _calibrate(args: argparse.Namespace) -> int:
    from lightstage.calibration.config import CalibrateConfig
    from lightstage.calibration.run import run_calibrate
    from lightstage.errors import LightstageError
    from lightstage.threads import set_library_threads
    from lightstage.workdir import WorkDir

    if not args.work.is_dir():
        raise LightstageError(f"{args.work}: work directory does not exist")
    set_library_threads(args.threads)
    config = CalibrateConfig.from_dict(
        {
            "method": args.method,
            "intrinsics": args.intrinsics,
            "num_threads": args.threads,
            "keep_sfm_workspace": args.keep_sfm,
        }
    )
    summary = run_calibrate(WorkDir.at(args.work), config, progress=not args.quiet)
    print(" ".join(f"{k}={v}" for k, v in summary.items()))
    return 0


def _calibrate_intrinsics(args: argparse.Namespace) -> int:
    from lightstage.calibration.intrinsics import CharucoBoardSpec, calibrate_folder
    from lightstage.errors import LightstageError

    try:
        sx, sy = (int(x) for x in args.squares.lower().split("x"))
    except ValueError:
        raise LightstageError(f"--squares: expected XxY, e.g. 11x8, got {args.squares!r}") from None
    spec = CharucoBoardSpec(sx, sy, args.square_length, args.marker_length, args.dictionary)
    doc = calibrate_folder(args.boards, spec, args.out)
    for cam, v in doc["cameras"].items():
        print(
            f"{cam}: fx={v['K'][0][0]:.2f} fy={v['K'][1][1]:.2f} rms={v['rms_px']:.3f} px ({v['num_images']} images)"
        )
    print(f"wrote {args.out}")
    return 0
