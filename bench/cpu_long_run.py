"""The longer CPU run of issue 18: train the `cpu` config for many more steps on a finished demo work
directory's shards (a copy that shares them), then score the whole test split (masked PSNR/SSIM beside the
ceiling a perfect prediction reaches on the same images) and print the PSNR curve. `--config` and `--device`
run another config on another device the same way (bench/gpu_check.sh: `fast` and `paper` on a GPU).

    python bench/cpu_long_run.py DEMO_WORK [--steps 20000] [--batch 2048] [--minutes 60] [--out DIR]
                                 [--override '{model: {n_fine: 64}}'] [--config cpu] [--device cpu]

The copy (default DEMO_WORK-long) links the demo's capture pointer, split, calibration, bounds, reports and
shards; only train/, eval/ and reports/{train,eval}.json are its own. `--minutes` stops training at a checkpoint
once the wall-clock budget is spent (the schedule still follows --steps).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import time
from pathlib import Path

import yaml

from lightstage.training.config import load_config, merge
from lightstage.training.evaluate import run_eval
from lightstage.training.train_stage import run_train
from lightstage.workdir import WorkDir

SHARED = ("capture.txt", "split.json", "bounds.json", "calibration", "preprocess", "shards")


def prepare(demo: Path, out: Path) -> WorkDir:
    """A work directory sharing the demo's inputs (symlinks) with its own train/eval outputs."""
    out.mkdir(parents=True, exist_ok=True)
    for name in SHARED:
        src, dst = demo / name, out / name
        if src.exists() and not dst.exists():
            os.symlink(src.resolve(), dst)
    (out / "reports").mkdir(exist_ok=True)
    for rep in (demo / "reports").glob("*.json"):
        if rep.stem not in ("train", "eval"):
            shutil.copy(rep, out / "reports" / rep.name)
    return WorkDir.at(out)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("demo", type=Path)
    ap.add_argument("--steps", type=int, default=20000)
    ap.add_argument("--batch", type=int, default=2048)
    ap.add_argument("--minutes", type=float, default=60.0)
    ap.add_argument("--eval-every", type=int, default=2000)
    ap.add_argument("--out", type=Path, default=None)
    ap.add_argument("--override", default="{}", help="YAML mapping merged into --config (after the flags)")
    ap.add_argument("--config", default="cpu", help="training config (default cpu)")
    ap.add_argument("--device", default="cpu", help="torch device (default cpu)")
    ap.add_argument("--chunk", type=int, default=1000, help="steps between time-budget checks (default 1000)")
    args = ap.parse_args()
    if not (args.demo / "shards" / "manifest.json").is_file():
        print(f"{args.demo}: no shards (run `lightstage demo --work {args.demo}` first)", file=sys.stderr)
        return 2
    work = prepare(args.demo, args.out or args.demo.with_name(args.demo.name + "-long"))
    flags = {"optim": {"steps": args.steps, "batch_rays": args.batch}, "eval": {"every": args.eval_every}}
    cfg = load_config(args.config, merge(flags, yaml.safe_load(args.override) or {}))
    print(f"config: {json.dumps(cfg.to_dict())}", flush=True)
    t0 = time.perf_counter()
    chunk = args.chunk  # the budget is checked between chunks (each resumes from the last checkpoint)
    step = 0
    while step < args.steps and time.perf_counter() - t0 < args.minutes * 60:
        step = min(args.steps, step + chunk)
        run_train(work, cfg, progress=False, stop_at=step, device=args.device)
        print(f"step {step}: {time.perf_counter() - t0:.0f} s", flush=True)
    ev = run_eval(work, progress=False, device=args.device)
    log = json.loads((work.train_dir / "log.json").read_text())
    print(
        json.dumps(
            {
                "config": args.config,
                "device": args.device,
                "steps": step,
                "batch": args.batch,
                "wall_s": round(time.perf_counter() - t0),
                **ev["mean"],
            }
        )
    )
    for e in log.get("eval", []):
        print(
            f"  step {e['step']}: masked PSNR {e['psnr']:.2f} dB ({e.get('train_seconds', 0):.0f} s training)"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
