"""`run_train`: the training stage entry point (stage API): shards + bounds from WORK -> WORK/train, report."""

from __future__ import annotations

import os
import time
from typing import Any

import torch

from lightstage.atomic import write_json_atomic
from lightstage.errors import LightstageError
from lightstage.executor import Executor
from lightstage.training.config import TrainConfig
from lightstage.workdir import WorkDir


def pick_device(device: str | None) -> torch.device:
    """`cuda` (this process's LOCAL_RANK GPU under torchrun) when available and not overridden, else `cpu`."""
    if device in (None, "", "auto"):
        device = "cuda" if torch.cuda.is_available() else "cpu"
    if device == "cuda":
        if not torch.cuda.is_available():
            raise LightstageError("--device cuda: no CUDA device available")
        return torch.device("cuda", int(os.environ.get("LOCAL_RANK", 0)))
    if device != "cpu":
        raise LightstageError(f"--device must be cpu, cuda or auto, got {device!r}")
    return torch.device("cpu")


def init_distributed(device: torch.device) -> bool:
    """Join the torchrun process group (NCCL on CUDA, gloo on CPU) when WORLD_SIZE > 1; True if joined here."""
    if int(os.environ.get("WORLD_SIZE", "1")) <= 1 or torch.distributed.is_initialized():
        return False
    if device.type == "cuda":
        torch.cuda.set_device(device)
    torch.distributed.init_process_group("nccl" if device.type == "cuda" else "gloo")
    return True


def run_train(
    work: WorkDir,
    config: TrainConfig,
    executor: Executor | None = None,
    progress: bool = True,
    device: str | None = None,
    stop_at: int | None = None,
) -> dict[str, Any]:
    """Train from WORK/shards into WORK/train (resuming from its checkpoint); rank 0 writes reports/train.json.
    `stop_at` ends this run at that step (checkpointed; a later run resumes to `optim.steps`), so a long training
    can be split over time-limited jobs. `executor` is accepted for the stage API and unused (training is one GPU
    job, multi-GPU through torchrun)."""
    from lightstage.training.inputs import ShardSource, iter_test_images
    from lightstage.training.trainer import distributed, fit

    dev = pick_device(device)
    joined = init_distributed(dev)
    try:
        rank, world = distributed()
        source = ShardSource(
            work,
            config.optim.batch_rays // world,
            seed=config.seed,
            workers=config.loader_workers,
            device=dev,
        )
        scene = source.normalization()
        tests = []
        if config.eval.every and rank == 0:
            tests = [img for _, img in zip(range(config.eval.images), iter_test_images(work), strict=False)]
        t0 = time.perf_counter()
        summary = fit(
            config,
            source,
            work.train_dir,
            scene["centre"],
            scene["scale"],
            box=scene["box"],
            hull=scene["hull"],
            device=dev,
            test_images=tests,
            progress=progress,
            stop_at=stop_at,
        )
        if rank == 0:
            report = {
                "stage": "train",
                "config": config.to_dict(),
                **summary,
                "wall_seconds": time.perf_counter() - t0,
                "bounds": {"centre": scene["centre"], "scale": scene["scale"], "box": scene["box"]},
            }
            write_json_atomic(work.report("train"), report)
        return {k: summary[k] for k in ("steps", "final_loss", "rays_per_s", "checkpoint")}
    finally:
        if joined:
            torch.distributed.destroy_process_group()
