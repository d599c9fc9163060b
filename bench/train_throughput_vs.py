"""Training throughput of this checkout against an earlier commit's, measured in one run: both trees'
`bench/train_throughput.py` alternate round by round at the same configs, batch and threads, and the ratio of
their medians is printed (this repository's VMs vary 10-30 % minute to minute, so figures taken apart do not
compare).

The earlier commit is checked out with `git worktree` into a temporary folder and imported through a package
folder of symlinks built from its pyproject's `package-dir` table (no second install); both run in this
interpreter's environment.

    python bench/train_throughput_vs.py 3abea33 [--configs fast] [--batch 1024 4096] [--rounds 3] [--steps 3]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def package_shim(tree: Path, into: Path) -> Path:
    """A folder holding `lightstage` as symlinks into `tree`, laid out as its pyproject's package-dir says."""
    dirs = tomllib.loads((tree / "pyproject.toml").read_text())["tool"]["setuptools"]["package-dir"]
    pkg = into / "lightstage"
    pkg.mkdir(parents=True)
    for item in (tree / dirs["lightstage"]).iterdir():
        (pkg / item.name).symlink_to(item)
    for name, folder in dirs.items():
        if name != "lightstage" and (tree / folder).is_dir():
            (pkg / name.split(".", 1)[1]).symlink_to(tree / folder)
    return into


def run_bench(tree: Path, pythonpath: str | None, config: str, batch: int, steps: int, threads: int) -> float:
    """rays/s of `config` from `tree`'s own bench (its defaults for everything not named here)."""
    env = dict(os.environ)
    if pythonpath:
        env["PYTHONPATH"] = pythonpath
    cmd = [
        sys.executable,
        str(tree / "bench/train_throughput.py"),
        "--configs",
        config,
        "--batch",
        str(batch),
    ]
    cmd += ["--steps", str(steps), "--threads", str(threads)]
    source = (tree / "bench/train_throughput.py").read_text()
    for flag, default in (
        ("--cpu-lookups", "numba"),
        ("--cpu-mlps", "fused"),
    ):  # newer benches: defaults only
        if flag in source:
            cmd += [flag, default]
    out = subprocess.run(cmd, cwd=tree, env=env, capture_output=True, text=True, check=True).stdout
    rows = [json.loads(line) for line in out.splitlines() if line.startswith("{")]
    return rows[0]["rays_per_s"]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("commit", help="the earlier commit (anything `git worktree add` takes)")
    ap.add_argument("--configs", nargs="+", default=["fast"])
    ap.add_argument("--batch", nargs="+", type=int, default=[1024, 4096])
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--steps", type=int, default=3)
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="lightstage-vs-") as tmp:
        old = Path(tmp) / "tree"
        subprocess.run(
            ["git", "worktree", "add", "--detach", "-f", str(old), args.commit], cwd=ROOT, check=True
        )
        try:
            shim = str(package_shim(old, Path(tmp) / "shim"))
            for config in args.configs:
                for batch in args.batch:
                    got: dict[str, list[float]] = {"then": [], "now": []}
                    for _ in range(args.rounds):
                        got["then"].append(run_bench(old, shim, config, batch, args.steps, args.threads))
                        got["now"].append(run_bench(ROOT, None, config, batch, args.steps, args.threads))
                    then, now = statistics.median(got["then"]), statistics.median(got["now"])
                    print(
                        json.dumps(
                            {"config": config, "batch": batch, "commit": args.commit, "rounds": args.rounds}
                            | {"then_rays_per_s": got["then"], "now_rays_per_s": got["now"]}
                            | {"ratio_of_medians": now / then}
                        ),
                        flush=True,
                    )
        finally:
            subprocess.run(["git", "worktree", "remove", "--force", str(old)], cwd=ROOT, check=False)


if __name__ == "__main__":
    main()
