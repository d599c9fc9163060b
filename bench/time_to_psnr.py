"""Time to a test-PSNR threshold from a training run's evaluation history (WORK/train/log.json).

The trainer records, at each periodic evaluation (`lightstage train --eval-every N`), the mean PSNR of its preview
test images against their masked targets (`psnr`; `psnr_full` beside it: every pixel of the raw target) and the
optimiser time so far (`train_seconds`, summed over resumed runs, evaluations excluded).
This prints when the threshold was first reached, the last periodic PSNR, and the full test-split PSNR from
WORK/reports/eval.json when `lightstage eval` has run (issue #10: `fast` >= 35 dB within 10 minutes on one GPU).

    python bench/time_to_psnr.py WORK [--threshold 35]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("work", type=Path)
    ap.add_argument("--threshold", type=float, default=35.0, help="PSNR in dB (default 35)")
    args = ap.parse_args()
    log = args.work / "train" / "log.json"
    if not log.is_file():
        print(f"{log}: missing (train with --eval-every N first)", file=sys.stderr)
        return 2
    evals = json.loads(log.read_text()).get("eval", [])
    reached = next((e for e in evals if e["psnr"] >= args.threshold), None)
    out = {
        "threshold_db": args.threshold,
        "evaluations": len(evals),
        "reached_at": reached,  # {step, psnr, train_seconds} or None
        "last": evals[-1] if evals else None,
    }
    train_report = args.work / "reports" / "train.json"
    if train_report.is_file():
        t = json.loads(train_report.read_text())
        out["train"] = {k: t.get(k) for k in ("steps", "train_seconds", "rays_per_s", "device")}
    eval_report = args.work / "reports" / "eval.json"
    if eval_report.is_file():
        e = json.loads(eval_report.read_text())
        out["test_split"] = {"count": e.get("count"), **e.get("mean", {}), "lpips": e.get("lpips")}
        out["ceiling"] = e.get("ceiling")  # what a perfect prediction scores (ceiling_* keys), or why not
    print(json.dumps(out, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
