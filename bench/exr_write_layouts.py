"""CPU cost of writing one processed frame (2048x1366 half R, G, B + saturation flags) in several EXR layouts.

Why the processed frames are two tiled parts: OpenEXR's write cost is mostly per chunk, and a scanline file has
one chunk per row (1,366 here) whatever its channels, so an uncompressed scanline write of the S plane alone costs
about as much as the R, G, B planes. Tiles make few large chunks; a second part lets the flags use RLE (almost
nothing to store) while the noisy colour, which barely compresses, goes uncompressed.

    python bench/exr_write_layouts.py [--repeats 5]

Prints JSON: CPU and wall seconds per write, file size, and each layout's CPU time over the previous default
(one RLE scanline part), measured in this run. One library thread, as the preprocess workers run.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import tempfile
import time
from pathlib import Path

import numpy as np

SIZE = (1366, 2048)  # (h, w) of a processed frame of an 8192x5464 raw frame


def frame(seed: int = 0) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """R, G, B half planes of noisy HDR content and a sparse saturation plane (as 0/1 half)."""
    rng = np.random.default_rng(seed)
    h, w = SIZE
    base = np.exp(rng.normal(-2, 1, (h, w))).astype(np.float32)
    planes = {
        c: np.ascontiguousarray((base * k + rng.normal(0, 0.01, (h, w))).astype(np.float16))
        for c, k in zip("RGB", (1.0, 0.8, 0.6), strict=True)
    }
    sat = np.zeros((h, w), np.float16)
    sat[100:120, 200:260] = 1
    return planes, sat


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeats", type=int, default=5, help="timed writes per layout (default 5)")
    args = ap.parse_args()

    from lightstage.frames import ExrPart, write_exr_parts
    from lightstage.records.processed import FLAGS_COMPRESSION, TILE
    from lightstage.threads import set_library_threads

    set_library_threads(1)
    rgb, sat = frame()
    rgbs = {**rgb, "S": sat}
    layouts = {
        "scanline RGBS rle (previous default)": ([ExrPart("", rgbs, "rle")], None),
        "scanline RGBS none": ([ExrPart("", rgbs, "none")], None),
        "tiled RGBS rle": ([ExrPart("", rgbs, "rle")], TILE),
        "tiled RGBS none": ([ExrPart("", rgbs, "none")], TILE),
        "tiled rgb none + S rle (default)": (
            [ExrPart("rgb", rgb, "none"), ExrPart("saturation", {"S": sat}, FLAGS_COMPRESSION)],
            TILE,
        ),
        "tiled rgb piz + S rle": (
            [ExrPart("rgb", rgb, "piz"), ExrPart("saturation", {"S": sat}, FLAGS_COMPRESSION)],
            TILE,
        ),
    }
    result: dict = {
        "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
        "machine": f"{platform.node()} {platform.machine()}, {os.cpu_count()} cores",
        "load_at_start": [round(x, 2) for x in os.getloadavg()],
        "frame": f"{SIZE[1]}x{SIZE[0]} half RGB + S",
        "layouts": {},
    }
    with tempfile.TemporaryDirectory(prefix="lightstage-exr-") as tmp:
        for name, (parts, tile) in layouts.items():
            path = Path(tmp) / "f.exr"
            write_exr_parts(path, parts, tile=tile)  # warm-up
            cpu, wall = time.process_time(), time.perf_counter()
            for _ in range(args.repeats):
                write_exr_parts(path, parts, tile=tile)
            result["layouts"][name] = {
                "cpu_s": round((time.process_time() - cpu) / args.repeats, 4),
                "wall_s": round((time.perf_counter() - wall) / args.repeats, 4),
                "mb": round(path.stat().st_size / 1e6, 2),
            }
    ref = result["layouts"]["scanline RGBS rle (previous default)"]["cpu_s"]
    result["cpu_over_previous_default"] = {
        k: round(v["cpu_s"] / ref, 3) for k, v in result["layouts"].items()
    }
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
