"""Peak RSS of `lightstage render` (one image and an orbit), `relight` and `mesh` at the paper's processed
2048 x 1366, on a briefly trained `tiny` model (memory does not depend on training). Each command runs in its
own process under /usr/bin/time -v; prints one line per command (results: docs/benchmarks.md).

    python bench/render_memory.py ROOT [--size 2048x1366] [--lights 2] [--orbit 2]
"""

from __future__ import annotations

import argparse
import re
import subprocess
import sys
from pathlib import Path


def make_model(root: Path) -> Path:
    """ROOT/work with a `tiny` model trained for 2 steps on the analytic sphere (tests/support)."""
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
    from support.synthetic import SyntheticSphere

    from lightstage.training.config import load_config
    from lightstage.training.trainer import fit
    from lightstage.workdir import WorkDir

    work = WorkDir.at(root / "work")
    if not (work.train_dir / "checkpoint.pt").is_file():
        sphere = SyntheticSphere(batch_size=256)
        config = load_config("tiny", {"optim": {"steps": 2, "batch_rays": 256, "warmup_steps": 1}})
        fit(config, sphere, work.train_dir, sphere.centre, sphere.scale, progress=False)
    return work.root


def peak(cmd: list[str]) -> tuple[float, float, float]:
    """(peak RSS MB, wall s, CPU s) of one command."""
    out = subprocess.run(["/usr/bin/time", "-v", *cmd], capture_output=True, text=True)
    if out.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)} failed:\n{out.stderr[-2000:]}")
    rss = int(re.search(r"Maximum resident set size \(kbytes\): (\d+)", out.stderr).group(1)) / 1024
    wall = re.search(r"Elapsed \(wall clock\) time.*: (?:(\d+):)?(\d+):([\d.]+)", out.stderr).groups()
    secs = int(wall[0] or 0) * 3600 + int(wall[1]) * 60 + float(wall[2])
    user = float(re.search(r"User time \(seconds\): ([\d.]+)", out.stderr).group(1))
    sys_ = float(re.search(r"System time \(seconds\): ([\d.]+)", out.stderr).group(1))
    return rss, secs, user + sys_


OUTS = ("r1", "r2", "r3", "m.ply")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("root", type=Path)
    ap.add_argument("--size", default="2048x1366")
    ap.add_argument("--lights", default="2", help="relight --lights (memory does not grow with it)")
    ap.add_argument("--orbit", type=int, default=2)
    ap.add_argument("--mesh-resolution", type=int, default=256)
    args = ap.parse_args()
    work = make_model(args.root)
    exe = str(Path(sys.executable).with_name("lightstage"))
    cam = f"orbit:az=30,elev=20,size={args.size}"
    env = args.root / "sky.exr"
    if not env.is_file():
        from lightstage.frames import write_exr
        from lightstage.training.envmap import procedural_sky

        write_exr(env, procedural_sky(64, 32).astype("float32"))
    runs = {
        "render (one image)": ["render", "--camera", cam, "--light", "azel:45,30", "--out", "r1"],
        f"render --orbit {args.orbit}": [
            "render",
            "--camera",
            cam,
            "--light",
            "azel:45,30",
            "--orbit",
            str(args.orbit),
            "--out",
            "r2",
        ],
        f"relight --lights {args.lights}": [
            "relight",
            "--envmap",
            str(env),
            "--lights",
            args.lights,
            "--camera",
            cam,
            "--out",
            "r3",
        ],
        f"mesh --resolution {args.mesh_resolution}": [
            "mesh",
            "--resolution",
            str(args.mesh_resolution),
            "--out",
            "m.ply",
        ],
    }
    print(f"{args.size}, tiny model; peak RSS, wall, CPU")
    for name, cmd in runs.items():
        cmd = [exe, cmd[0], str(work), *(str(args.root / c) if c in OUTS else c for c in cmd[1:])]
        rss, wall, cpu = peak(cmd)
        print(f"{name}: {rss:.0f} MB peak RSS, {wall:.1f} s wall, {cpu:.1f} CPU-s", flush=True)


if __name__ == "__main__":
    main()
