"""Helpers for tests and benchmarks that must be importable by spawned processes (DDP on CPU with gloo)."""

from __future__ import annotations

from pathlib import Path

import torch

from lightstage.training.config import TrainConfig, load_config
from lightstage.training.trainer import fit
from support.synthetic import SyntheticSphere


def micro_config(steps: int, batch: int = 64, **extra) -> TrainConfig:
    """The `tiny` config shrunk further (2 x 16 MLPs, 8 + 8 samples): seconds per run on a busy CPU."""
    over = {
        "optim": {"steps": steps, "batch_rays": batch, "warmup_steps": 2},
        "model": {
            "mlp": {"depth": 2, "width": 16, "skip": 1, "head_width": 8, "pos_freqs": 2},
            "n_coarse": 8,
            "n_fine": 8,
        },
        "eval": {"stats_batches": 2},
        "log_every": 1,
        **extra,
    }
    return load_config("tiny", over)


def ddp_worker(rank: int, world: int, init_file: str, out: str, steps: int = 3) -> None:
    """One DDP rank (gloo): train the micro config on the synthetic sphere, save this rank's parameters."""
    torch.set_num_threads(1)
    torch.distributed.init_process_group(
        "gloo", init_method=f"file://{init_file}", rank=rank, world_size=world
    )
    try:
        src = SyntheticSphere(batch_size=32)
        live: list = []
        fit(
            micro_config(steps),
            src,
            Path(out) / f"train{rank}",
            src.centre,
            src.scale,
            progress=False,
            model_out=live,
        )
        torch.save(live[0].state_dict(), Path(out) / f"rank{rank}.pt")
    finally:
        torch.distributed.destroy_process_group()
