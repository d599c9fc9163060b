"""Fake stages with the stage API convention, for testing the pipeline machinery (records, skipping,
--from/--only, dask faults, kills) quickly and independently of the real stages.

The fake capture is a folder of `frames/NNN.txt` files holding one integer each; a frame holding anything
else is "corrupt". Imported by name (`test_pipeline_fakes`) from tests/ on sys.path so dask workers and
`lightstage run` subprocesses can load it. This module holds no tests.
"""

from __future__ import annotations

import json
import os
import time
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

from lightstage.atomic import is_temp_name, write_json_atomic, write_text_atomic
from lightstage.errors import LightstageError
from lightstage.executor import Executor, LoopExecutor, TaskFailure
from lightstage.workdir import WorkDir

STAGES = ("validate", "preprocess", "calibrate", "split", "bounds", "shard", "train", "eval")


def entry_points() -> dict[str, str]:
    return {s: f"test_pipeline_fakes:run_{s}" for s in STAGES}


def make_capture(root: Path, n: int = 12, corrupt: tuple[int, ...] = ()) -> Path:
    (root / "frames").mkdir(parents=True, exist_ok=True)
    for i in range(n):
        text = "garbage!" if i in corrupt else str(i + 1)
        (root / "frames" / f"{i:03d}.txt").write_text(text)
    return root


def _from_dict(cls: type, d: dict[str, Any]) -> Any:
    names = {f.name: f for f in fields(cls)}
    for k, v in d.items():
        if k not in names:
            raise LightstageError(f"{k}: unknown key")
        if not isinstance(v, int | float) or isinstance(v, bool):
            raise LightstageError(f"{k}: expected a number, got {v!r}")
    return cls(**d)


@dataclass(frozen=True)
class FakeConfig:
    scale: int = 2
    delay: float = 0.0

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> FakeConfig:
        return _from_dict(cls, d)


def _capture(work: WorkDir) -> Path:
    return Path(work.capture_pointer.read_text().strip())


def _report(work: WorkDir, stage: str, **data: Any) -> dict[str, Any]:
    summary = {"stage": stage, "warnings": [], "errors": [], **data}
    write_json_atomic(work.report(stage), summary)
    return summary


def run_validate(
    work: WorkDir, config: FakeConfig, executor: Executor | None = None, progress: bool = True
) -> dict:
    frames = sorted(p.name for p in (_capture(work) / "frames").glob("*.txt"))
    bad = [f for f in frames if not (_capture(work) / "frames" / f).read_text().strip().isdigit()]
    write_json_atomic(work.manifest, {"frames": frames, "bad": bad})
    return _report(work, "validate", counts={"frames": len(frames), "bad": len(bad)}, errors=bad)


def _preprocess_one(item: tuple[str, str, int, float]) -> dict[str, Any]:
    src, dst, scale, delay = item
    if Path(dst).exists():
        return {"frame": Path(src).name, "status": "skipped"}
    text = Path(src).read_text().strip()
    if not text.isdigit():
        return {"frame": Path(src).name, "status": "error", "reason": "corrupt frame"}
    time.sleep(delay)
    write_text_atomic(dst, f"{int(text) * scale}\n")
    return {"frame": Path(src).name, "status": "done", "pid": os.getpid()}


def run_preprocess(
    work: WorkDir,
    config: FakeConfig,
    executor: Executor | None = None,
    progress: bool = True,
    offline: frozenset[str] = frozenset(),
) -> dict:
    manifest = json.loads(work.manifest.read_text())
    out = work.preprocess_dir / "frames"
    out.mkdir(parents=True, exist_ok=True)
    items = [
        (str(_capture(work) / "frames" / f), str(out / f), config.scale, config.delay)
        for f in manifest["frames"]
        if f not in offline
    ]
    executor = executor or LoopExecutor()
    recs = executor.map(_preprocess_one, items, window=4, progress=progress, errors="return")
    errors = [r.error if isinstance(r, TaskFailure) else r for r in recs if not r or r["status"] == "error"]
    counts = {s: sum(1 for r in recs if r and r["status"] == s) for s in ("done", "skipped")}
    return _report(
        work,
        "preprocess",
        counts={**counts, "errors": len(errors)},
        errors=errors,
        rejected=[e["frame"] for e in errors if isinstance(e, dict)],
    )


def run_preprocess_partial(
    work: WorkDir, config: FakeConfig, executor: Executor | None = None, progress: bool = True
) -> dict:
    """run_preprocess, except that frames named in unavailable.txt beside the capture (storage that is offline) are left
    out and reported missing: the stage raises StageIncomplete."""
    from lightstage.errors import StageIncomplete

    listed = _capture(work).parent / "unavailable.txt"  # beside the capture: it is not part of it
    offline = frozenset(listed.read_text().split()) if listed.is_file() else frozenset()
    summary = run_preprocess(work, config, executor, progress, offline)
    missing = sorted(offline & set(json.loads(work.manifest.read_text())["frames"]))
    if missing:
        raise StageIncomplete(f"preprocess: {len(missing)} frame(s) offline", missing, summary)
    return summary


def run_calibrate_nothing(
    work: WorkDir, config: FakeConfig, executor: Executor | None = None, progress: bool = True
) -> dict:
    """A calibrate stage that returns without writing calibration.json."""
    return _report(work, "calibrate", counts={})


def finished_outputs(folder: Path) -> list[Path]:
    """The fake frames written so far, by name, as a real stage reads its outputs: not the atomic_path temporary
    a worker killed mid-write leaves (`.<stem>.<pid>.<random>.tmp.txt`, empty), which pathlib's glob matches
    (it failed test_worker_killed_mid_run_completes_with_identical_outputs once in CI)."""
    return [p for p in sorted(folder.glob("*.txt")) if not is_temp_name(p.name)]


def _done_values(folder: Path) -> list[int]:
    """The finished frames' values."""
    return [int(p.read_text()) for p in finished_outputs(folder)]


def run_calibrate(
    work: WorkDir, config: FakeConfig, executor: Executor | None = None, progress: bool = True
) -> dict:
    total = sum(_done_values(work.preprocess_dir / "frames")) * config.scale
    write_json_atomic(work.calibration, {"total": total})
    return _report(work, "calibrate", counts={"total": total})


def run_split(
    work: WorkDir, config: FakeConfig, executor: Executor | None = None, progress: bool = True
) -> dict:
    names = [p.name for p in finished_outputs(work.preprocess_dir / "frames")]
    split = {"train": names[::2], "test": names[1::2]}
    write_json_atomic(work.split, split)
    return _report(work, "split", counts={k: len(v) for k, v in split.items()})


def _shard_one(item: tuple[str, list[str], str, float]) -> str:
    folder, names, dst, delay = item
    if Path(dst).exists():
        return dst
    time.sleep(delay)
    write_text_atomic(dst, ",".join(str(int(Path(folder, n).read_text())) for n in names) + "\n")
    return dst


def run_shard(
    work: WorkDir, config: FakeConfig, executor: Executor | None = None, progress: bool = True
) -> dict:
    split = json.loads(work.split.read_text())
    folder = str(work.preprocess_dir / "frames")
    train = split["train"]
    items = [
        (folder, train[i : i + 2], str(work.shards_dir / f"shard-{i // 2:03d}.txt"), config.delay)
        for i in range(0, len(train), 2)
    ]
    (executor or LoopExecutor()).map(_shard_one, items, progress=progress)
    write_json_atomic(work.shards_dir / "manifest.json", {"shards": len(items)})
    return _report(work, "shard", counts={"shards": len(items)})


def run_bounds(
    work: WorkDir, config: FakeConfig, executor: Executor | None = None, progress: bool = True
) -> dict:
    bounds = {"scale": config.scale, "shards": len(json.loads(work.split.read_text())["train"])}
    write_json_atomic(work.bounds, bounds)
    return _report(work, "bounds", counts=bounds)


@dataclass(frozen=True)
class FakeTrainConfig:
    steps: int = 3
    delay: float = 0.0

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> FakeTrainConfig:
        return _from_dict(cls, d)


def run_train(
    work: WorkDir, config: FakeTrainConfig, executor: Executor | None = None, progress: bool = True
) -> dict:
    ckpt = work.train_dir / "checkpoint.json"
    state = json.loads(ckpt.read_text()) if ckpt.exists() else {"step": 0, "weight": 0}
    values = [int(v) for p in sorted(work.shards_dir.glob("shard-*.txt")) for v in p.read_text().split(",")]
    while state["step"] < config.steps:
        time.sleep(config.delay)
        state = {"step": state["step"] + 1, "weight": state["weight"] + sum(values)}
        write_json_atomic(ckpt, state)
    return _report(work, "train", counts={"steps": state["step"]})


def run_eval(
    work: WorkDir, config: FakeConfig, executor: Executor | None = None, progress: bool = True
) -> dict:
    state = json.loads((work.train_dir / "checkpoint.json").read_text())
    metrics = {"score": state["weight"] * config.scale}
    write_json_atomic(work.eval_dir / "metrics.json", metrics)
    return _report(work, "eval", metrics=metrics)


# The config class of each fake stage (the pipeline reads CONFIG_CLASSES of an entry point's module).
CONFIG_CLASSES = {s: FakeTrainConfig if s == "train" else FakeConfig for s in STAGES}
