"""Loader throughput and memory: rays/s of RayShardDataset from the page cache (single process and with
DataLoader workers), and peak RSS against dataset size. `compact` runs hand over the 16-byte records as the
trainer's loader does (rays computed later on the training device); `rays` runs also compute the rays on this
CPU (lightstage.dataset.ray_table). Run: python bench/loader_throughput.py [--shards N]."""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))  # tests/support: synthetic data

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def _cpu_seconds() -> float:
    """CPU seconds of this process plus its finished (reaped) children: DataLoader workers."""
    import resource

    me, kids = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return me.ru_utime + me.ru_stime + kids.ru_utime + kids.ru_stime


def throughput(
    shards: Path, batch_size: int, workers: int, verify: str, seconds: float = 8.0, rays: bool = False
) -> dict:
    """Rays per wall second and per CPU second (main + workers: the per-core rate, robust to a busy machine)
    over whole epochs (at least `seconds` of work), page cache warm."""
    import torch

    from lightstage.dataset.loader import RayLoader, RayShardDataset

    torch.set_num_threads(1)
    ds = RayShardDataset(shards, batch_size=batch_size, verify=verify, rays=rays)
    loader = RayLoader(ds, num_workers=workers)
    n = 0
    c0 = _cpu_seconds()
    t0 = time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        for b in loader:
            n += next(iter(b.values())).shape[0]
    dt = time.perf_counter() - t0
    cpu = _cpu_seconds() - c0
    return {
        "batch_size": batch_size,
        "workers": workers,
        "verify": verify,
        "output": "rays" if rays else "compact",
        "rays": n,
        "seconds": round(dt, 2),
        "cpu_seconds": round(cpu, 2),
        "rays_per_s": round(n / dt),
        "rays_per_cpu_s": round(n / cpu),
    }


def expand_speed(shards: Path, device: str, batch_size: int = 65536, batches: int = 50) -> dict:
    """Rays per second of computing a batch's rays from its compact records on `device` (RayTable.expand:
    what the trainer does on its GPU per step), the records already on the device."""
    import torch

    from lightstage.dataset.loader import RayShardDataset

    ds = RayShardDataset(shards, batch_size=batch_size, verify="never", rays=False)
    table = ds.table(device)
    records = [b["records"].to(device) for _, b in zip(range(8), ds, strict=False)]
    sync = torch.cuda.synchronize if table.device.type == "cuda" else (lambda: None)
    table.expand(records[0])  # warm-up (kernels, allocator)
    sync()
    t0 = time.perf_counter()
    for k in range(batches):
        table.expand(records[k % len(records)])
    sync()
    dt = time.perf_counter() - t0
    return {"device": device, "batch_size": batch_size, "rays_per_s": round(batches * batch_size / dt)}


def peak_rss_child(shards: Path, batch_size: int) -> int:
    """Peak RSS (kB) of a fresh process that reads one full epoch."""
    code = (
        "import sys;from lightstage.dataset.loader import RayShardDataset\n"
        f"ds=RayShardDataset({str(shards)!r}, batch_size={batch_size}, verify='open', rays=False)\n"
        "n=sum(next(iter(b.values())).shape[0] for b in ds)\n"
        "print([l for l in open('/proc/self/status') if l.startswith('VmHWM')][0].split()[1])\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    return int(out.stdout.strip().splitlines()[-1])


def shard_speed(tmp: Path, width: int = 2048, height: int = 1366, lights: int = 9) -> dict:
    """Seconds per training frame of `run_shard` (phase A + B, in-process) at the paper's processed resolution."""
    from support.fixtures import make_synthetic_work

    from lightstage.dataset.shard_config import ShardConfig
    from lightstage.dataset.shards import run_shard
    from lightstage.dataset.split import SplitConfig, run_split

    work, _ = make_synthetic_work(
        tmp / "speed", num_cameras=3, num_lights=lights, num_groups=1, width=width, height=height
    )
    proto = tmp / "proto.yaml"
    proto.write_text("cameras: {test: 1}\nlights: {train: rest, test: 1}\n")
    run_split(work, SplitConfig(str(proto)), progress=False)
    s = run_shard(work, ShardConfig(workers=1, rays_per_shard=1 << 15), progress=False)
    frames = s["frames"]
    return {
        "resolution": f"{width}x{height}",
        "train_frames": frames,
        "rays": s["rays"],
        "timings": s["timings"],
        "seconds_per_frame_sampling": round(s["timings"]["sample_views_s"] / frames, 4),
        "seconds_per_frame_total": round(s["seconds"] / frames, 4),
        "bytes_per_ray": s["bytes_per_ray"],
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--shards", type=int, default=8, help="shards of --rays-per-shard rays")
    ap.add_argument("--rays-per-shard", type=int, default=1 << 20)
    ap.add_argument("--seconds", type=float, default=8.0)
    ap.add_argument("--shard-speed", action="store_true", help="also time run_shard per frame at 2048x1366")
    ap.add_argument("--out", type=Path, default=None, help="write results as JSON here")
    ap.add_argument(
        "--device", default=None, help="also time the rays' computation on this device (e.g. cuda)"
    )
    args = ap.parse_args()

    from support.fixtures import write_random_shards

    results: dict = {"cpu_count": os.cpu_count(), "load_average": os.getloadavg(), "runs": [], "memory": []}
    with tempfile.TemporaryDirectory(prefix="loader-bench-") as tmp:
        shards = write_random_shards(tmp, args.shards, args.rays_per_shard)
        size = sum(p.stat().st_size for p in (shards / "train").glob("*.npy"))
        results["dataset"] = {"shards": args.shards, "rays": args.shards * args.rays_per_shard, "bytes": size}
        for p in (shards / "train").glob("*.npy"):  # warm the page cache
            p.read_bytes()
        for bs, workers, verify, rays in (
            (8192, 0, "never", False),
            (65536, 0, "never", False),
            (65536, 0, "open", False),
            (65536, 2, "never", False),
            (65536, 0, "never", True),
        ):
            r = throughput(shards, bs, workers, verify, args.seconds, rays)
            results["runs"].append(r)
            print(json.dumps(r), flush=True)
        if args.device:
            results["expand"] = expand_speed(shards, args.device)
            print(json.dumps(results["expand"]), flush=True)
        small = write_random_shards(Path(tmp) / "small", 2, args.rays_per_shard, seed=1)
        for n, path in ((2, small), (args.shards, shards)):
            rss = peak_rss_child(path, 65536)
            results["memory"].append({"shards": n, "peak_rss_kB": rss})
            print(json.dumps(results["memory"][-1]), flush=True)
        if args.shard_speed:
            results["shard_speed"] = shard_speed(Path(tmp))
            print(json.dumps(results["shard_speed"]), flush=True)
    results["load_average_after"] = os.getloadavg()
    if args.out:
        args.out.write_text(json.dumps(results, indent=2) + "\n")


if __name__ == "__main__":
    main()
