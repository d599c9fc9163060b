"""Checkpoints: model, optimiser, scheduler, grad scaler, RNG states (torch, CUDA, numpy, python) and the loader
position in one file, written atomically (torch.save to a temp file + os.replace) and loadable with
`weights_only=True` (no pickled code), so a resumed run continues exactly where the saved one stopped."""

from __future__ import annotations

import random
from pathlib import Path
from typing import Any

import numpy as np
import torch

from lightstage.atomic import atomic_path
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
    """Restore what `rng_state` captured."""
    torch.set_rng_state(state["torch"])
    n = state["numpy"]
    np.random.set_state(  # noqa: NPY002
        (n["kind"], n["keys"].numpy().astype(np.uint32), n["pos"], n["has_gauss"], n["cached"])
    )
    random.setstate(_lists_to_tuples(state["python"]))
    if "cuda" in state and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(state["cuda"])


def save_checkpoint(path: Path, payload: dict[str, Any]) -> None:
    """Write `payload` (plus the format version) atomically."""
    with atomic_path(path) as tmp:
        torch.save({"format": FORMAT_VERSION, **payload}, tmp)


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


def _tuples_to_lists(x: Any) -> Any:
    return [_tuples_to_lists(v) for v in x] if isinstance(x, tuple | list) else x


def _lists_to_tuples(x: Any) -> Any:
    return tuple(_lists_to_tuples(v) for v in x) if isinstance(x, list) else x
