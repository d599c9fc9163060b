"""Checkpoints: model, optimiser, scheduler, grad scaler, RNG states (torch, CUDA, numpy, python) and the loader
position in one file, written atomically (torch.save to a temp file + os.replace) and loadable with
`weights_only=True` (no pickled code), so a resumed run continues exactly where the saved one stopped."""

from __future__ import annotations

import io
import random
from pathlib import Path
from typing import Any

import numpy as np
import torch

from lightstage.atomic import write_bytes_atomic
from lightstage.errors import LightstageError

FORMAT_VERSION = 1


CHECKPOINT_NAME = "checkpoint.pt"  # WORK/train/checkpoint.pt: the latest checkpoint


def rng_state() -> dict[str, Any]:
    """This process's RNG states as tensors and plain values (safe for weights_only loading)."""
    kind, keys, pos, has_gauss, cached = np.random.get_state()  # noqa: NPY002 (global state is what we save)
    state: dict[str, Any] = {
        "torch": torch.get_rng_state(),
        "numpy": {
            "kind": kind,
            "keys": torch.from_numpy(keys.astype(np.int64)),
            "pos": int(pos),
            "has_gauss": int(has_gauss),
            "cached": float(cached),
        },
        "python": _tuples_to_lists(random.getstate()),
    }
    if torch.cuda.is_available():
        state["cuda"] = torch.cuda.get_rng_state_all()
    return state


def set_rng_state(state: dict[str, Any]) -> None:
    """Restore what `rng_state` captured. A checkpoint loaded with a CUDA map_location holds these tensors on
    the GPU, and torch takes RNG states only as CPU byte tensors, hence `.cpu()`."""
    torch.set_rng_state(state["torch"].cpu())
    n = state["numpy"]
    np.random.set_state(  # noqa: NPY002
        (n["kind"], n["keys"].cpu().numpy().astype(np.uint32), n["pos"], n["has_gauss"], n["cached"])
    )
    random.setstate(_lists_to_tuples(state["python"]))
    if "cuda" in state and torch.cuda.is_available():
        torch.cuda.set_rng_state_all([s.cpu() for s in state["cuda"]])


def save_checkpoint(path: Path, payload: dict[str, Any]) -> None:
    """Write `payload` (plus the format version) atomically. torch.save fills a buffer that Python then
    writes: on a full disk torch's own writer raises an opaque RuntimeError, Python an OSError (ENOSPC)
    naming the file."""
    buffer = io.BytesIO()
    torch.save({"format": FORMAT_VERSION, **payload}, buffer)
    write_bytes_atomic(path, buffer.getbuffer())


def load_checkpoint(path: Path, map_location: str | torch.device = "cpu") -> dict[str, Any]:
    """Read a checkpoint written by `save_checkpoint`; a missing or damaged file is a LightstageError."""
    if not Path(path).is_file():
        raise LightstageError(f"{path}: no checkpoint (train first: lightstage train WORK)")
    try:
        data = torch.load(path, map_location=map_location, weights_only=True)
    except Exception as e:  # torch raises many types for truncated/corrupt files
        raise LightstageError(f"{path}: unreadable checkpoint ({type(e).__name__}: {e})") from e
    if not isinstance(data, dict) or data.get("format") != FORMAT_VERSION:
        raise LightstageError(f"{path}: not a lightstage checkpoint of format {FORMAT_VERSION}")
    return data


# Config keys a resumed training may change: how long it trains, how often it logs, evaluates and checkpoints,
# how it renders previews and the final evaluation, how many loader processes read the shards (the batch
# order is theirs to keep). Any other change would meet model, optimiser and schedule state made under the old
# value (Adam restores its lr and betas, the schedule its base lr, the stats their exposure), so it is refused.
RESUME_SAFE_KEYS = frozenset(
    {
        "name",
        "optim.steps",  # upward only: more steps stretch the decay from the resumed step on
        "eval.every",
        "eval.images",
        "eval.chunk",
        "eval.max_images",
        "eval.lpips",
        "eval.lpips_weights",  # retired (config.RETIRED_KEYS): only an old checkpoint still holds them
        "eval.lpips_linear_weights",
        "log_every",
        "checkpoint_every",
        "loader_workers",
    }
)
_ABSENT = object()


def resume_conflicts(saved: dict[str, Any], current: dict[str, Any]) -> list[str]:
    """`key: old → new` for every config key (dotted) in which this run's config differs from the one the
    checkpoint was trained with, except the RESUME_SAFE_KEYS (optim.steps only when it grows)."""
    old, new = _flatten(saved), _flatten(current)
    out = []
    for key in [*new, *(k for k in old if k not in new)]:
        a, b = old.get(key, _ABSENT), new.get(key, _ABSENT)
        if a == b or (key in RESUME_SAFE_KEYS and key != "optim.steps"):
            continue
        if key == "optim.steps" and isinstance(a, int) and isinstance(b, int) and b >= a:
            continue
        out.append(f"{key}: {_show(a)} → {_show(b)}")
    return out


def _flatten(d: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    """{"optim": {"lr": 1}} -> {"optim.lr": 1}."""
    out: dict[str, Any] = {}
    for k, v in d.items():
        if isinstance(v, dict):
            out.update(_flatten(v, f"{prefix}{k}."))
        else:
            out[f"{prefix}{k}"] = v
    return out


def _show(v: Any) -> str:
    return "(absent)" if v is _ABSENT else repr(v) if isinstance(v, str) else str(v)


def _tuples_to_lists(x: Any) -> Any:
    return [_tuples_to_lists(v) for v in x] if isinstance(x, tuple | list) else x


def _lists_to_tuples(x: Any) -> Any:
    return tuple(_lists_to_tuples(v) for v in x) if isinstance(x, list) else x
