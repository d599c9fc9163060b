"""Training throughput (rays per second, forward + backward + Adam step) of every built-in config (or the
ones named) on the synthetic sphere problem, on CPU and, when present, on CUDA.

For configs with an occupancy grid (`fast`) the grid is set from the analytic sphere (what training converges
to) so empty-space skipping is measured as it behaves after warm-up; `--no-occupancy-prefill` measures the
all-occupied start. Every config runs at the same batch, so the ratios printed at the end compare equal work.
On CPU the hash-grid configs run with both lookups in the same run, the fused numba kernels (the default) and
the PyTorch path (`--cpu-lookups` picks), and the ratio of the two is printed; likewise their MLPs, chunked
in one autograd function (`training/fused_mlp`, the default) and as modules (`--cpu-mlps`). `--rounds N`
repeats every variant N times interleaved and reports each one's median (the VMs measured vary by 10-30 %
minute to minute). glibc's malloc is set as training sets it (`lightstage.malloc`).

    python bench/train_throughput.py [--configs paper paper-lite fast tiny] [--batch 4096] [--steps 5]
                                     [--devices cpu cuda] [--cpu-lookups numba torch] [--cpu-mlps fused module]
                                     [--rounds 1] [--precision bf16|fp16|fp32]

`--precision` replaces each config's own; the JSON's `precision` is what autocast actually ran
(`training/trainer.autocast_dtype`: the config's on CUDA, fp32 on CPU).
"""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))  # tests/support: synthetic data

import argparse
import json
import statistics
import time

import lightstage  # noqa: F401  (before torch: it bounds GNU OpenMP's spin-wait, as in training)

# isort: split
import torch
from support.synthetic import SyntheticSphere

from lightstage.malloc import keep_large_blocks
from lightstage.training import hashgrid as hashgrid_field
from lightstage.training import hashgrid_cpu
from lightstage.training.config import BUILTIN_CONFIGS, load_config
from lightstage.training.losses import measured_epsilon, total_loss
from lightstage.training.model import RelightModel
from lightstage.training.trainer import autocast_context, autocast_dtype, compute_stats, make_optimizer


def prefill_occupancy(model: RelightModel, src: SyntheticSphere) -> None:
    """Mark the cells inside the synthetic sphere (plus one cell) as occupied."""
    occ = model.occupancy
    r = occ.resolution
    centres = (torch.stack(torch.meshgrid(*(torch.arange(r),) * 3, indexing="ij"), -1) + 0.5) / r * 2 - 1
    inside = centres.norm(dim=-1) <= src.radius / src.scale + 2.0 / r
    occ.grid.copy_(torch.where(inside, 1e4, 0.0).to(occ.grid.device))
    occ.ready.fill_(True)


def measure(
    name: str,
    device: str,
    batch: int,
    steps: int,
    warmup: int,
    prefill: bool,
    lookup: str,
    mlp: str,
    precision: str,
) -> dict:
    cfg = load_config(name, {"optim": {"precision": precision}} if precision else None)
    hashgrid_cpu.set_enabled(lookup == "numba")
    hashgrid_field._FUSED_MLP = mlp == "fused"
    src = SyntheticSphere(batch_size=batch)
    dev = torch.device(device)
    model = RelightModel(cfg.model, src.centre, src.scale).to(dev)
    if model.occupancy is not None and prefill:
        prefill_occupancy(model, src)
    # the trainer's optimiser (fused Adam) and loss epsilon, so a step costs what a training step does
    opt = make_optimizer(model, cfg.optim)
    stats = compute_stats(src, cfg.eval.stats_batches, cfg.eval.exposure_percentile)
    loss_cfg = measured_epsilon(cfg.loss, stats.exposure)
    batches = [{k: v.to(dev) for k, v in src.batch(i).items()} for i in range(4)]

    def step(i: int) -> None:
        b = batches[i % len(batches)]
        with autocast_context(dev, cfg.optim.precision):
            out = model(b["origins"], b["directions"], b["light_directions"], randomized=True)
        loss, _ = total_loss(out, b, loss_cfg)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()

    for i in range(warmup):
        step(i)
    if dev.type == "cuda":
        torch.cuda.synchronize()
    t0 = time.perf_counter()
    for i in range(steps):
        step(i)
    if dev.type == "cuda":
        torch.cuda.synchronize()
    dt = time.perf_counter() - t0
    return {
        "config": name,
        "device": device,
        "batch": batch,
        "steps": steps,
        "seconds": dt,
        "rays_per_s": batch * steps / dt,
        "precision": {None: "fp32", torch.bfloat16: "bf16", torch.float16: "fp16"}[
            autocast_dtype(dev, cfg.optim.precision)
        ],
        "occupancy_prefilled": bool(model.occupancy is not None and prefill),
        "threads": torch.get_num_threads(),
        "lookup": lookup,
        "mlp": mlp,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument(
        "--configs",
        nargs="+",
        default=list(BUILTIN_CONFIGS),
        help="built-in names or YAML files (default: all)",
    )
    ap.add_argument("--devices", nargs="+", default=["cpu", "cuda"] if torch.cuda.is_available() else ["cpu"])
    ap.add_argument(
        "--batch", type=int, default=None, help="rays per step (default 4096 on CUDA, 1024 on CPU)"
    )
    ap.add_argument("--steps", type=int, default=None, help="timed steps (default 20 on CUDA, 3 on CPU)")
    ap.add_argument("--warmup", type=int, default=1)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--no-occupancy-prefill", action="store_true")
    ap.add_argument("--precision", choices=["bf16", "fp16", "fp32"], help="instead of each config's own")
    ap.add_argument(
        "--cpu-lookups",
        nargs="+",
        choices=["numba", "torch"],
        default=["numba", "torch"] if hashgrid_cpu.available() else ["torch"],
        help="hash-grid lookups to measure on CPU (default: both)",
    )
    ap.add_argument(
        "--cpu-mlps",
        nargs="+",
        choices=["fused", "module"],
        default=["fused", "module"],
        help="hash-grid MLP paths to measure on CPU (default: both)",
    )
    ap.add_argument("--rounds", type=int, default=1, help="interleaved repeats of every variant (median)")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    keep_large_blocks()
    results = []
    for device in args.devices:
        gpu = device == "cuda"
        batch = args.batch or (4096 if gpu else 1024)
        steps = args.steps or (20 if gpu else 3)
        for name in args.configs:
            hashgrid = load_config(name).model.field == "hashgrid"
            cpu_grid = device == "cpu" and hashgrid
            variants = [
                (lookup, mlp)
                for lookup in (args.cpu_lookups if cpu_grid else args.cpu_lookups[:1])
                for mlp in (args.cpu_mlps if cpu_grid else ["module"])
            ]
            runs: dict[tuple[str, str], list[dict]] = {v: [] for v in variants}
            for _ in range(args.rounds):
                for lookup, mlp in variants:
                    prefill = not args.no_occupancy_prefill
                    r = measure(name, device, batch, steps, args.warmup, prefill, lookup, mlp, args.precision)
                    runs[(lookup, mlp)].append(r)
            for v in variants:
                r = dict(runs[v][0])
                r["rays_per_s"] = statistics.median(x["rays_per_s"] for x in runs[v])
                r["rounds"] = [round(x["rays_per_s"]) for x in runs[v]]
                print(json.dumps(r), flush=True)
                results.append(r)
    by: dict[tuple[str, str], float] = {}
    for r in results:  # ratios between configs at the first lookup measured (the default)
        by.setdefault((r["device"], r["config"]), r["rays_per_s"])
    cpu = {(r["config"], r["lookup"], r["mlp"]): r["rays_per_s"] for r in results if r["device"] == "cpu"}
    mlp0, lookup0 = args.cpu_mlps[0], args.cpu_lookups[0]
    for name in args.configs:
        if (name, "numba", mlp0) in cpu and (name, "torch", mlp0) in cpu:
            ratio = cpu[(name, "numba", mlp0)] / cpu[(name, "torch", mlp0)]
            print(f"cpu: {name}: fused numba lookup {ratio:.2f}x the PyTorch lookup ({mlp0} MLPs)")
        if (name, lookup0, "fused") in cpu and (name, lookup0, "module") in cpu:
            ratio = cpu[(name, lookup0, "fused")] / cpu[(name, lookup0, "module")]
            print(f"cpu: {name}: chunked fused MLPs {ratio:.2f}x the module MLPs ({lookup0} lookup)")
    for device in args.devices:
        if (device, "paper") in by:
            ratios = ", ".join(
                f"{name} {by[(device, name)] / by[(device, 'paper')]:.1f}x"
                for name in args.configs
                if name != "paper" and (device, name) in by
            )
            print(f"{device}: rays/s relative to paper: {ratios}")


if __name__ == "__main__":
    main()
