"""Helpers for tests and benchmarks that must be importable by spawned processes (DDP on CPU with gloo)."""

from __future__ import annotations

from pathlib import Path

import torch

from lightstage.training.config import TrainConfig, load_config
from lightstage.training.trainer import fit
from support.synthetic import SyntheticSphere


def rays_into_origin(n: int, seed: int, spread: float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(origins, unit directions, unit light directions) of n rays from about (0, -2, 0) towards +y, directions
    jittered by `spread`, lights random: a bundle through the unit cube for field and model tests."""
    torch.manual_seed(seed)
    o = torch.tensor([0.0, -2.0, 0.0]).expand(n, 3) + torch.randn(n, 3) * 0.05
    d = torch.nn.functional.normalize(torch.tensor([0.0, 1.0, 0.0]) + torch.randn(n, 3) * spread, dim=-1)
    light = torch.nn.functional.normalize(torch.randn(n, 3), dim=-1)
    return o, d, light


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


def train_and_eval(capture: Path, root: Path) -> dict:
    """The real stages on a simulated capture: preprocess, true calibration, split (every non-test light trains),
    shard, 300 steps of the demo's `cpu` config, eval; returns the eval means (WORK = root)."""
    import shutil

    from lightstage.dataset.shard_config import ShardConfig
    from lightstage.dataset.shards import run_shard
    from lightstage.dataset.split import SplitConfig, run_split
    from lightstage.preprocess.config import PreprocessConfig
    from lightstage.preprocess.run import run_preprocess
    from lightstage.training.evaluate import run_eval
    from lightstage.training.train_stage import run_train
    from lightstage.workdir import WorkDir

    work = WorkDir.at(root)
    work.root.mkdir()
    work.capture_pointer.write_text(str(capture))
    run_preprocess(work, PreprocessConfig(), progress=False)
    work.calibration.parent.mkdir(parents=True, exist_ok=True)
    shutil.copy(capture / "ground_truth" / "geometry.json", work.calibration)
    split = SplitConfig.from_dict({"protocol": {"base": "paper", "lights": {"train": "rest"}}})
    run_split(work, split, progress=False)
    run_shard(work, ShardConfig(workers=1), progress=False)
    cfg = load_config("cpu", {"optim": {"steps": 300, "batch_rays": 512}, "eval": {"every": 0}})
    run_train(work, cfg, progress=False, device="cpu")
    return run_eval(work, progress=False, device="cpu")["mean"]


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
