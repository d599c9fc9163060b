"""Preprocess throughput at the reference resolution (8192x5464 half RGB raw frames).

Generates a few real-size raw frames in a temp dir (simulator-like content: dark noisy background, a lit
textured object, a saturated bulb, a flare), then measures in one run:
  * OpenEXR decode-only time per frame, one library thread;
  * a per-step breakdown of the per-frame work (decode, downscale, write, statistics), one thread;
  * the whole stage (`run_preprocess`) on a dask LocalCluster with 1 and with 2 single-threaded worker
    processes: wall time per frame, in-task time per frame, speed-up, peak RSS per worker;
  * peak RSS per worker again with views twice as long (memory must not grow with the frames per view).
Prints a JSON summary (and the ratios against the targets). Frames beyond the distinct ones are symlinks, so
decoding cost is real while generation stays short.

    python bench/preprocess_throughput.py --distinct 4 --cameras 2 --lights 12
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np

RES = (8192, 5464)


def generate_frames(out: Path, distinct: int, seed: int = 0) -> list[Path]:
    """Write `distinct` raw half ZIP frames at 8192x5464 with the simulator's noise model."""
    from lightstage.capture.frames import write_exr
    from lightstage.capture.presets import PAPER_SATURATION

    W, H = RES
    rng = np.random.default_rng(seed)
    sat = np.float16(PAPER_SATURATION)
    if float(sat) < PAPER_SATURATION:
        sat = np.nextafter(sat, np.float16(np.inf))
    paths = []
    y = (np.arange(H, dtype=np.float32)[:, None] + 0.5 - H / 2) / (0.28 * H)
    x = (np.arange(W, dtype=np.float32)[None, :] + 0.5 - W / 2) / (0.16 * W)
    r2 = x * x + y * y
    inside = r2 < 1.0
    nz = np.sqrt(np.clip(1.0 - r2, 0, 1))
    texture = (0.55 + 0.35 * np.sin(x * 37.0) * np.cos(y * 23.0)).astype(np.float32)
    for i in range(distinct):
        a = 2 * np.pi * i / max(distinct, 1)
        ldir = np.array([np.cos(a) * 0.7, np.sin(a) * 0.3, 0.65], np.float32)
        shade = np.clip(x * ldir[0] + y * ldir[1] + nz * ldir[2], 0, None) * texture * inside
        img = np.empty((H, W, 3), np.float16)
        for r in range(0, H, 512):  # bands keep the float32 temporaries small
            s = slice(r, r + 512)
            base = shade[s, :, None] * np.array([0.9, 0.6, 0.35], np.float32) + np.float32(0.002)
            sigma = np.sqrt(1e-4 * base + 0.0015**2)
            band = base + sigma * rng.standard_normal(base.shape, dtype=np.float32)
            img[s] = np.clip(band, 0, float(sat)).astype(np.float16)
        if i == 0:  # a bulb in view: saturated disk
            img[400:440, 7000:7040] = sat
        if i == 1 % max(distinct, 1):  # a flare: broad additive glow
            gy, gx = np.ogrid[0:H:8, 0:W:8]
            glow = 0.15 * np.exp(-((gx - 6500) ** 2 + (gy - 1200) ** 2) / (2 * 800.0**2)).astype(np.float32)
            big = np.repeat(np.repeat(glow, 8, 0), 8, 1)[:H, :W]
            for r in range(0, H, 512):
                s = slice(r, r + 512)
                img[s] = np.minimum(img[s].astype(np.float32) + big[s, :, None], float(sat)).astype(
                    np.float16
                )
        p = out / "distinct" / f"f{i}.exr"
        write_exr(p, img, compression="zip")
        paths.append(p)
        del img
    return paths


def make_capture(root: Path, distinct: list[Path], cameras: int, lights: int) -> Path:
    """A capture (1 group, `cameras` x `lights` frames) whose frames are symlinks to the distinct frames."""
    from lightstage.capture.layout import DEFAULT_PATH_TEMPLATE, CaptureInfo, save_capture_info
    from lightstage.capture.presets import make_stage

    stage = make_stage("bench", num_cameras=cameras, num_lights=lights, num_groups=1)
    root.mkdir(parents=True)
    stage.save(root / "stage.yaml")
    save_capture_info(CaptureInfo(DEFAULT_PATH_TEMPLATE, 1.0, "bench"), root / "capture.yaml")
    k = 0
    for g in stage.groups:
        for c in stage.cameras:
            d = root / "frames" / g.name / c.id
            d.mkdir(parents=True)
            for lt in stage.lights:
                (d / f"{lt.index:03d}.exr").symlink_to(distinct[k % len(distinct)])
                k += 1
    return root


def decode_only(paths: list[Path], repeats: int = 2) -> float:
    """Mean seconds per OpenEXR decode (interleaved RGB), one library thread, warm page cache."""
    import OpenEXR

    times = []
    for rep in range(repeats):
        for p in paths:
            t = time.perf_counter()
            px = OpenEXR.File(str(p)).parts[0].channels["RGB"].pixels
            dt = time.perf_counter() - t
            assert px.shape == (RES[1], RES[0], 3)
            del px
            if rep:  # first pass warms the page cache
                times.append(dt)
    return float(np.mean(times))


def breakdown(paths: list[Path], compression: str, tmp: Path) -> dict[str, float]:
    """Mean seconds per step of the per-frame work, in this process (one library thread)."""
    from lightstage.preprocess.downscale import decode_raw, downscale
    from lightstage.preprocess.flare import lit_threshold, thumbnail
    from lightstage.preprocess.processed import to_float, to_half, write_processed
    from lightstage.preprocess.stats import StatsAccumulator, luminance

    steps: dict[str, list[float]] = {
        "decode": [],
        "downscale": [],
        "half+check": [],
        "write": [],
        "statistics": [],
    }
    acc = StatsAccumulator(RES[1] // 4, RES[0] // 4)
    for i, p in enumerate(paths):
        t0 = time.perf_counter()
        px = decode_raw(p, RES)
        t1 = time.perf_counter()
        small = downscale(px, 4.4019)
        del px
        t2 = time.perf_counter()
        rgb_h = to_half(small.rgb)
        import cv2

        cv2.checkRange(small.rgb, True, -65504.0, 65504.0)
        t3 = time.perf_counter()
        write_processed(tmp / f"w{i}.exr", rgb_h, small.saturated, compression)
        t4 = time.perf_counter()
        rgb = to_float(rgb_h)
        lum = luminance(rgb)
        th = thumbnail(lum, small.saturated, 8)
        acc.add(i, rgb, small.saturated, lit_threshold(th, 4.4019), lum)
        t5 = time.perf_counter()
        for k, a, b in zip(steps, (t0, t1, t2, t3, t4), (t1, t2, t3, t4, t5), strict=True):
            steps[k].append(b - a)
    return {k: round(float(np.mean(v)), 4) for k, v in steps.items()}


def _worker_peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def run_stage(capture: Path, work_root: Path, workers: int, chunk_lights: int, compression: str) -> dict:
    """Run the whole stage on a fresh LocalCluster of `workers` single-threaded processes."""
    from lightstage.pipelines.cluster import ClusterSettings, dask_client
    from lightstage.preprocess.config import PreprocessConfig
    from lightstage.preprocess.run import run_preprocess
    from lightstage.workdir import WorkDir

    work = WorkDir.at(work_root)
    work.root.mkdir(parents=True)
    work.capture_pointer.write_text(str(capture))
    config = PreprocessConfig(chunk_lights=chunk_lights, compression=compression)
    with dask_client(ClusterSettings(workers=workers, dashboard=""), verbose=False) as client:
        load0 = os.getloadavg()[0]
        t = time.perf_counter()
        summary = run_preprocess(work, config, client=client, progress=False)
        wall = time.perf_counter() - t
        rss = sorted(client.run(_worker_peak_rss_mb).values())
    report = json.loads(work.report("preprocess").read_text())
    n = report["counts"]["processed"]
    chunk_s = 0.0
    for v in (work.preprocess_dir / "views").rglob("view.json"):
        chunk_s += sum(c["seconds"] for c in json.loads(v.read_text())["chunks"])
    shutil.rmtree(work.root)
    return {
        "workers": workers,
        "frames": n,
        "wall_s": round(wall, 2),
        "wall_per_frame_s": round(wall / n, 4),
        "task_per_frame_s": round(chunk_s / n, 4),
        "peak_rss_mb_per_worker": [round(r) for r in rss],
        "load_before": round(load0, 2),
        "load_after": round(os.getloadavg()[0], 2),
        "errors": summary["errors"],
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--distinct", type=int, default=4, help="distinct generated frames (default 4)")
    ap.add_argument("--cameras", type=int, default=2, help="views (cameras) in the capture (default 2)")
    ap.add_argument("--lights", type=int, default=12, help="lights per view (default 12)")
    ap.add_argument("--chunk-lights", type=int, default=3, help="lights per chunk task (default 3)")
    ap.add_argument("--compression", default="zip", help="processed-frame compression (zip | piz | none)")
    ap.add_argument("--tmp", type=Path, default=None, help="where to put the temp dir (default: system temp)")
    ap.add_argument("--skip-rss-check", action="store_true", help="skip the longer-view memory run")
    args = ap.parse_args()

    from lightstage.threads import set_library_threads

    set_library_threads(1)
    tmp = Path(tempfile.mkdtemp(prefix="lightstage-bench-", dir=args.tmp))
    result: dict = {
        "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
        "machine": f"{platform.node()} {platform.machine()}, {os.cpu_count()} cores, {_cpu_model()}",
        "load_at_start": [round(x, 2) for x in os.getloadavg()],
        "resolution": list(RES),
    }
    try:
        t = time.perf_counter()
        distinct = generate_frames(tmp, args.distinct)
        result["generate_s"] = round(time.perf_counter() - t, 1)
        result["raw_frame_mb"] = round(np.mean([p.stat().st_size for p in distinct]) / 1e6, 1)
        result["decode_only_s"] = round(decode_only(distinct), 4)
        result["breakdown_s"] = breakdown(distinct, args.compression, tmp)
        capture = make_capture(tmp / "capture", distinct, args.cameras, args.lights)
        runs = [run_stage(capture, tmp / f"work{w}", w, args.chunk_lights, args.compression) for w in (1, 2)]
        result["stage"] = runs
        if not args.skip_rss_check:
            longer = make_capture(tmp / "capture2", distinct, 1, 2 * args.lights)
            result["stage_longer_view"] = run_stage(
                longer, tmp / "work_long", 1, args.chunk_lights, args.compression
            )
        one, two = runs
        result["ratios"] = {
            "task_per_frame_over_decode": round(one["task_per_frame_s"] / result["decode_only_s"], 3),
            "wall_per_frame_1_worker_over_decode": round(
                one["wall_per_frame_s"] / result["decode_only_s"], 3
            ),
            "speedup_2_workers": round(one["wall_s"] / two["wall_s"], 3),
            "targets": "task/decode <= 1.3, speed-up >= 1.7, peak RSS per worker <= 1536 MB",
        }
        result["load_at_end"] = [round(x, 2) for x in os.getloadavg()]
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    print(json.dumps(result, indent=2))


def _cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown CPU"


if __name__ == "__main__":
    main()
