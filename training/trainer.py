"""The training loop: Adam with warm-up + exponential/cosine decay, GPU autocast (bf16/fp16), gradient clipping,
atomic checkpoints that resume exactly, CSV/JSON logs + loss-curve PNG (TensorBoard when importable), periodic
evaluation with preview PNGs, and DDP across `torchrun` processes (rank 0 writes)."""

from __future__ import annotations

import contextlib
import csv
import json
import math
import random
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tqdm import tqdm

from lightstage.atomic import write_json_atomic
from lightstage.errors import LightstageError
from lightstage.malloc import keep_large_blocks
from lightstage.records.shards import TestImage
from lightstage.tonemap import auto_exposure
from lightstage.training.checkpoint import (
    CHECKPOINT_NAME,
    load_checkpoint,
    resume_conflicts,
    rng_state,
    save_checkpoint,
    set_rng_state,
)
from lightstage.training.config import OptimConfig, TrainConfig
from lightstage.training.hashgrid import HashGridEncoding
from lightstage.training.inputs import BatchSource
from lightstage.training.light_model import light_frame
from lightstage.training.losses import measured_epsilon, total_loss
from lightstage.training.model import RelightModel
from lightstage.workdir import ZONE_FOREGROUND

LOG_FIELDS = ("step", "loss", "rgb_fine", "rgb_coarse", "mask", "lr", "rays_per_s", "occupied")


@dataclass
class TrainStats:
    """What evaluation needs from the training data: the capture's exposure and the constant-colour baseline."""

    exposure: float
    baseline_rgb: list[float]


def lr_factor(step: int, cfg: OptimConfig) -> float:
    """Multiplier of cfg.lr at `step`: linear warm-up from 1% then exponential or cosine decay to lr_final."""
    if step < cfg.warmup_steps:
        return 0.01 + 0.99 * step / cfg.warmup_steps
    p = min(1.0, (step - cfg.warmup_steps) / max(1, cfg.steps - cfg.warmup_steps))
    final = cfg.lr_final / cfg.lr
    if cfg.schedule == "exponential":
        return final**p
    return final + (1.0 - final) * 0.5 * (1.0 + math.cos(math.pi * p))


def compute_stats(source: BatchSource, n_batches: int, percentile: float) -> TrainStats:
    """Exposure (percentile of foreground luminance -> 1) and mean colour of the first training batches as
    the loader composes them (1/2 foreground, 3/8 band, 1/8 background)."""
    rgb, fg = [], []
    for _, batch in zip(range(max(1, n_batches)), source.batches(0, 0, 1), strict=False):
        rgb.append(batch["rgb"].float().cpu().numpy())
        fg.append(batch["zone"].cpu().numpy() == ZONE_FOREGROUND)
    rgb_all, fg_all = np.concatenate(rgb), np.concatenate(fg)
    exposure = auto_exposure(rgb_all[fg_all] if fg_all.any() else rgb_all, percentile)
    return TrainStats(exposure=float(exposure), baseline_rgb=rgb_all.mean(0).astype(float).tolist())


def measure_light_frame(source: BatchSource, n_batches: int) -> tuple[list[float], float]:
    """(centre, distance) of the lights in the first training batches (`light_model.light_frame`); a distant
    light (inf) when their directions cannot fix a centre (e.g. one light)."""
    pos, dirs = [], []
    for _, batch in zip(range(max(1, n_batches)), source.batches(0, 0, 1), strict=False):
        pos.append(batch["light_positions"].double().cpu().numpy())
        dirs.append(batch["light_directions"].double().cpu().numpy())
    p, idx = np.unique(np.concatenate(pos).round(6), axis=0, return_index=True)
    try:
        centre, radius = light_frame(p, np.concatenate(dirs)[idx])
    except ValueError:
        return [0.0, 0.0, 0.0], float("inf")
    return centre.tolist(), radius


def distributed() -> tuple[int, int]:
    """(rank, world size) of the initialised process group, or (0, 1)."""
    if torch.distributed.is_available() and torch.distributed.is_initialized():
        return torch.distributed.get_rank(), torch.distributed.get_world_size()
    return 0, 1


def autocast_dtype(device: torch.device, precision: str) -> torch.dtype | None:
    """The autocast dtype training runs under: bf16/fp16 on CUDA (fp16 where bf16 is unsupported), None (full
    precision) elsewhere. CPU stays float32: bf16 autocast there (AVX512-BF16, AMX) trained `fast` no better per
    step and slower on the demo capture (docs/benchmarks.md, 2026-12-06)."""
    if precision == "fp32" or device.type != "cuda":
        return None
    return torch.bfloat16 if precision == "bf16" and torch.cuda.is_bf16_supported() else torch.float16


def autocast_context(device: torch.device, precision: str) -> contextlib.AbstractContextManager:
    """Autocast in `autocast_dtype`'s dtype, or nothing; the fields' heads return float32 either way."""
    dtype = autocast_dtype(device, precision)
    return contextlib.nullcontext() if dtype is None else torch.autocast(device.type, dtype=dtype)


def make_optimizer(model: torch.nn.Module, ocfg: OptimConfig) -> torch.optim.Adam:
    """The training optimiser: Adam with the config's betas, epsilon and weight decay, fused (one kernel per
    tensor: ~10x less CPU time than the default for-each step on `fast`'s 16 M parameters)."""
    return torch.optim.Adam(
        model.parameters(),
        lr=ocfg.lr,
        betas=(ocfg.beta1, ocfg.beta2),
        eps=ocfg.adam_eps,
        weight_decay=ocfg.weight_decay,
        fused=True,
    )


def fit(
    config: TrainConfig,
    source: BatchSource,
    out_dir: Path,
    centre: Sequence[float],
    scale: float,
    *,
    box: Sequence[Sequence[float]] | None = None,
    hull: torch.Tensor | None = None,
    device: str | torch.device = "cpu",
    test_images: Sequence[TestImage] = (),
    progress: bool = True,
    resume: bool = True,
    stop_at: int | None = None,
    model_out: list | None = None,
) -> dict[str, Any]:
    """Train until config.optim.steps (or `stop_at`, for interrupted runs in tests), resuming from
    out_dir/checkpoint.pt when present. Returns a summary dict (rank 0 writes every file)."""
    device = torch.device(device)
    keep_large_blocks()  # a step's multi-MB activations and table gradients reuse freed heap (lightstage.malloc)
    rank, world = distributed()
    writer_rank = rank == 0
    out_dir = Path(out_dir)
    cfg, ocfg = config, config.optim
    total = ocfg.steps if stop_at is None else min(stop_at, ocfg.steps)
    torch.manual_seed(cfg.seed + rank)
    np.random.seed(cfg.seed + rank)  # noqa: NPY002 (seed the global RNG third-party code may use)
    random.seed(cfg.seed + rank)

    model = RelightModel(cfg.model, centre, scale, box, hull).to(device)
    opt = make_optimizer(model, ocfg)
    sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda s: lr_factor(s, ocfg))
    use_scaler = autocast_dtype(device, ocfg.precision) == torch.float16  # fp16 needs loss scaling; bf16 not
    scaler = torch.amp.GradScaler("cuda", enabled=use_scaler) if use_scaler else None

    step, stats, train_seconds = 0, None, 0.0  # train_seconds: optimiser time over all runs (no evaluations)
    ckpt_path = out_dir / CHECKPOINT_NAME
    if resume and ckpt_path.is_file():
        ck = load_checkpoint(ckpt_path, map_location=device)
        _check_resumable(ckpt_path, ck, cfg)
        try:
            model.load_state_dict(ck["model"])
            opt.load_state_dict(ck["optimizer"])
            for module in model.modules():  # Adam's moments of a padded hash table, as the table is packed
                if isinstance(module, HashGridEncoding):
                    module.pack_optimizer_state(opt)
        except (RuntimeError, ValueError, KeyError) as e:  # the checkpoint's tensors do not fit this model
            reason = str(e).strip().splitlines()[0][:300] if str(e).strip() else type(e).__name__
            raise LightstageError(f"{ckpt_path}: does not fit this model ({reason})") from None
        sched.load_state_dict(ck["scheduler"])
        if scaler is not None and ck.get("scaler"):
            scaler.load_state_dict(ck["scaler"])
        states = ck["rng"]
        set_rng_state(states[rank] if rank < len(states) else states[0])
        step = int(ck["loader"]["position"])
        stats = TrainStats(**ck["stats"])
        train_seconds = float(ck.get("train_seconds", 0.0))
    if stats is None:
        stats = compute_stats(source, cfg.eval.stats_batches, cfg.eval.exposure_percentile)
    loss_cfg = measured_epsilon(cfg.loss, stats.exposure)
    if cfg.model.light == "point" and not bool(torch.isfinite(model.light_radius)):
        model.set_light_frame(*measure_light_frame(source, cfg.eval.stats_batches))

    net: torch.nn.Module = model
    if world > 1:
        net = torch.nn.parallel.DistributedDataParallel(
            model, device_ids=[device.index] if device.type == "cuda" else None
        )

    log = _Log(out_dir, step) if writer_rank else None
    batches = iter(source.batches(step, rank, world))
    bar = tqdm(
        total=total,
        initial=step,
        desc=f"train {cfg.name}",
        disable=not (progress and writer_rank),
        unit="step",
    )
    t_start, rays_done, t_window, rays_window = time.perf_counter(), 0, time.perf_counter(), 0
    t_mark = t_start  # train_seconds is accumulated up to here
    parts: dict[str, float] = {}
    loss_value, window_losses = float("nan"), []
    while step < total:
        batch = {k: v.to(device, non_blocking=True) for k, v in next(batches).items()}
        model.update_occupancy(step, cfg.seed)
        with autocast_context(device, ocfg.precision):
            out = net(batch["origins"], batch["directions"], batch["light_directions"], randomized=True)
        loss, parts = total_loss(out, batch, loss_cfg)
        opt.zero_grad(set_to_none=True)
        if scaler is not None:
            scaler.scale(loss).backward()
            scaler.unscale_(opt)
        else:
            loss.backward()
        if ocfg.grad_clip > 0:
            torch.nn.utils.clip_grad_norm_(model.parameters(), ocfg.grad_clip)
        if scaler is not None:
            scaler.step(opt)
            scaler.update()
        else:
            opt.step()
        sched.step()
        step += 1
        n_rays = batch["rgb"].shape[0] * world
        rays_done += n_rays
        rays_window += n_rays
        loss_value = float(loss.detach())
        window_losses.append(loss_value)
        bar.update(1)
        if log is not None and (step % cfg.log_every == 0 or step == total):
            now = time.perf_counter()
            occ = model.occupancy.occupied_fraction() if model.occupancy is not None else 1.0
            row = {
                "step": step,
                "loss": float(np.mean(window_losses)),
                **parts,
                "lr": sched.get_last_lr()[0],
                "rays_per_s": rays_window / max(now - t_window, 1e-9),
                "occupied": occ,
            }
            log.add(row)
            bar.set_postfix(loss=f"{loss_value:.4g}")
            t_window, rays_window, window_losses = now, 0, []
        if cfg.eval.every and step % cfg.eval.every == 0 and writer_rank and test_images:
            train_seconds, t_mark = _lap(train_seconds, t_mark, device)
            psnrs = preview(
                model,
                test_images[: cfg.eval.images],
                stats,
                out_dir / "previews",
                step,
                cfg.eval.chunk,
                log,
                train_seconds,
            )
            bar.write(f"step {step}: test PSNR {np.mean(psnrs):.2f} dB on {len(psnrs)} image(s)")
            t_mark = time.perf_counter()  # evaluation time is not training time
        if step % cfg.checkpoint_every == 0 or step == total:
            train_seconds, t_mark = _lap(train_seconds, t_mark, device)
            _save(ckpt_path, model, opt, sched, scaler, step, world, stats, cfg, writer_rank, train_seconds)
            if log is not None:
                log.flush(plot=True)
    bar.close()
    elapsed = time.perf_counter() - t_start
    summary = {
        "steps": step,
        "final_loss": loss_value,
        "final_parts": parts,
        "seconds": elapsed,
        "train_seconds": train_seconds,  # optimiser time over all runs of this training, evaluations excluded
        "rays_per_s": rays_done / elapsed if elapsed > 0 else None,
        "device": str(device),
        "world_size": world,
        "checkpoint": str(ckpt_path),
        "exposure": stats.exposure,
        "loss_epsilon": loss_cfg.epsilon,  # measured when loss.epsilon_of_level is set
        "baseline_rgb": stats.baseline_rgb,
        "tensorboard": log is not None and log.tb is not None,
    }
    if log is not None:
        log.close()
    if model_out is not None:
        model_out.append(model)
    return summary


def _check_resumable(path: Path, ck: dict[str, Any], cfg: TrainConfig) -> None:
    """Refuse to resume a checkpoint trained with another config (bar the keys RESUME_SAFE_KEYS allows),
    naming each differing key with its old and new value."""
    saved = ck.get("config")
    if not isinstance(saved, dict):
        return
    try:  # keys added to TrainConfig since the checkpoint was written take their defaults
        saved = TrainConfig.from_dict(saved).to_dict()
    except (LightstageError, TypeError, ValueError):
        pass
    conflicts = resume_conflicts(saved, cfg.to_dict())
    if conflicts:
        raise LightstageError(
            f"{path}: cannot resume with a config different from the checkpoint's ({'; '.join(conflicts)}): "
            "resume with the checkpoint's config (a resume may only raise optim.steps or change how often it "
            f"evaluates, logs and checkpoints), or delete {path.parent} to train from scratch"
        )


def _lap(train_seconds: float, t_mark: float, device: torch.device) -> tuple[float, float]:
    """Add the optimiser time since `t_mark` to `train_seconds` (after the GPU's queued work); a new mark."""
    if device.type == "cuda":
        torch.cuda.synchronize(device)
    now = time.perf_counter()
    return train_seconds + now - t_mark, now


def _save(path, model, opt, sched, scaler, step, world, stats, cfg, writer_rank, train_seconds=0.0) -> None:
    """Gather every rank's RNG state; rank 0 writes the checkpoint atomically."""
    states = [rng_state()]
    if world > 1:
        gathered: list[Any] = [None] * world
        torch.distributed.all_gather_object(gathered, states[0])
        states = gathered
    if not writer_rank:
        return
    save_checkpoint(
        path,
        {
            "step": step,
            "config": cfg.to_dict(),
            "model": model.state_dict(),
            "optimizer": opt.state_dict(),
            "scheduler": sched.state_dict(),
            "scaler": scaler.state_dict() if scaler is not None else {},
            "rng": [_to_cpu(s) for s in states],
            "loader": {"position": step, "world_size": world},
            "stats": {"exposure": stats.exposure, "baseline_rgb": stats.baseline_rgb},
            "train_seconds": train_seconds,
        },
    )


def _to_cpu(x: Any) -> Any:
    if isinstance(x, torch.Tensor):
        return x.cpu()
    if isinstance(x, dict):
        return {k: _to_cpu(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return type(x)(_to_cpu(v) for v in x)
    return x


@torch.no_grad()
def preview(
    model: RelightModel,
    images,
    stats: TrainStats,
    folder: Path,
    step: int,
    chunk: int,
    log=None,
    train_seconds: float = 0.0,
) -> list[float]:
    """Render a few test images, write prediction | masked target PNGs and return their PSNRs against the
    masked target (evaluation's headline metric; the full-frame PSNR is logged beside it)."""
    from lightstage.frames import write_image
    from lightstage.training.evaluate import side_by_side
    from lightstage.training.inference import render_image
    from lightstage.training.metrics import image_metrics

    was_training = model.training
    model.eval()
    psnrs, full = [], []
    for k, img in enumerate(images):
        pred = render_image(model, img.camera, img.light_direction, chunk)
        m = image_metrics(pred, img.masked_target, stats.exposure)
        psnrs.append(m["psnr"])
        full.append(
            image_metrics(pred, img.target, stats.exposure)["psnr"] if img.mask is not None else m["psnr"]
        )
        png = side_by_side(pred, img.masked_target, stats.exposure)
        folder.mkdir(parents=True, exist_ok=True)
        write_image(folder / f"step{step:07d}_{k}.png", png)
        if log is not None and log.tb is not None:
            log.tb.add_image(f"preview/{k}", png, step, dataformats="HWC")
    if log is not None:
        log.add_eval(
            step,
            float(np.mean(psnrs)),
            train_seconds,
            psnr_full=float(np.mean(full)),
            images=[img.name for img in images],
        )
    model.train(was_training)
    return psnrs


class _Log:
    """log.csv (+ loss.png, log.json of evaluations) in the output folder; TensorBoard when importable.
    On resume, rows after the checkpoint's step are dropped so the log matches the resumed run."""

    def __init__(self, folder: Path, start_step: int):
        self.folder = folder
        folder.mkdir(parents=True, exist_ok=True)
        self.csv = folder / "log.csv"
        self.rows: list[dict[str, Any]] = []
        if start_step > 0 and self.csv.is_file():
            with open(self.csv, newline="") as f:
                self.rows = [r for r in csv.DictReader(f) if int(r["step"]) <= start_step]
        self.evals: list[dict[str, float]] = []
        if start_step > 0 and (folder / "log.json").is_file():
            try:
                earlier = json.loads((folder / "log.json").read_text()).get("eval", [])
                self.evals = [e for e in earlier if int(e["step"]) <= start_step]
            except (OSError, ValueError, KeyError, TypeError, AttributeError):
                self.evals = []  # an unreadable log only loses the earlier evaluations' history
        self.tb = None
        try:
            from torch.utils.tensorboard import SummaryWriter

            self.tb = SummaryWriter(str(folder / "tensorboard"), purge_step=start_step or None)
        except ImportError:  # tensorboard is an optional extra
            self.tb = None

    def add(self, row: dict[str, Any]) -> None:
        self.rows.append(row)
        if self.tb is not None:
            for k, v in row.items():
                if k != "step":
                    self.tb.add_scalar(f"train/{k}", v, row["step"])

    def add_eval(self, step: int, psnr: float, train_seconds: float = 0.0, **extra: Any) -> None:
        """A periodic evaluation: `psnr` against the masked target; extra keys (psnr_full, images) kept."""
        self.evals.append({"step": step, "psnr": psnr, "train_seconds": train_seconds, **extra})
        if self.tb is not None:
            self.tb.add_scalar("eval/psnr", psnr, step)

    def flush(self, plot: bool = False) -> None:
        from lightstage.atomic import atomic_path

        with atomic_path(self.csv) as tmp, open(tmp, "w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=LOG_FIELDS, extrasaction="ignore")
            w.writeheader()
            w.writerows(self.rows)
        write_json_atomic(self.folder / "log.json", {"train": self.rows, "eval": self.evals})
        if plot and self.rows:
            self._plot()

    def _plot(self) -> None:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        from lightstage.atomic import atomic_path

        steps = [int(r["step"]) for r in self.rows]
        fig, ax = plt.subplots(figsize=(6, 3.5), dpi=100)
        for key in ("loss", "rgb_fine", "rgb_coarse"):
            vals = [float(r[key]) if r.get(key) not in (None, "") else np.nan for r in self.rows]
            if np.isfinite(vals).any():
                ax.plot(steps, vals, label=key)
        ax.set_yscale("log")
        ax.set_xlabel("step")
        ax.set_ylabel("loss")
        ax.legend()
        fig.tight_layout()
        with atomic_path(self.folder / "loss.png") as tmp:
            fig.savefig(tmp, format="png")
        plt.close(fig)

    def close(self) -> None:
        self.flush(plot=True)
        if self.tb is not None:
            self.tb.close()
