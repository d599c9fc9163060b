"""LPIPS (Zhang et al. 2018, v0.1, VGG) through the `lpips` package, with the VGG16 backbone weights supplied
locally (nothing is downloaded here, and a random backbone is never used).

The `lpips` package ships its own linear-layer weights (`lpips/weights/v0.1/vgg.pth`) and holds the network:
input scaling, the five VGG taps, unit-normalised features, the linear layers and the spatial mean. Only the
ImageNet VGG16 backbone is missing, because torchvision downloads it at run time: `eval.lpips_weights` names a
local torchvision VGG16 state dict (`vgg16(...).state_dict()` with `features.N.*` keys, or `.features.state_dict()`
with `N.*` keys), which is loaded strictly into the package's backbone slices (a missing, extra or misshapen
tensor makes LPIPS unavailable with the reason). Without the file `lpips_or_none` returns (None, reason) and
evaluation reports LPIPS as unavailable.

The backbone's layer layout comes from torchvision's `vgg16(weights=None).features` when torchvision imports.
Where it does not (a CPU-only torch with the index's CUDA-built torchvision, as on the project's CI machines),
the package is imported beside `vgg16_features`, the same 31-module layout written out here (13 3x3 convs,
ReLUs, 5 max-pools): it only gives the user's weights their places, and the strict load checks every name and
shape.
"""

from __future__ import annotations

import sys
import types
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch
from torch import nn

# torchvision's VGG16 configuration "D": conv widths, "M" = 2x2 max-pool.
VGG16_LAYOUT = (64, 64, "M", 128, 128, "M", 256, 256, 256, "M", 512, 512, 512, "M", 512, 512, 512, "M")


def vgg16_features() -> nn.Sequential:
    """The module layout of torchvision's `vgg16().features` (randomly initialised; weights must be loaded)."""
    layers: list[nn.Module] = []
    in_ch = 3
    for v in VGG16_LAYOUT:
        if v == "M":
            layers.append(nn.MaxPool2d(kernel_size=2, stride=2))
        else:
            layers += [nn.Conv2d(in_ch, int(v), kernel_size=3, padding=1), nn.ReLU(inplace=True)]
            in_ch = int(v)
    return nn.Sequential(*layers)


def _backbone_architecture(pretrained: bool = False, **_: object) -> types.SimpleNamespace:
    """What `lpips` calls as `torchvision.models.vgg16(pretrained=...)`: the architecture only, never a
    download (LPIPS is built with pnet_rand=True, and the user's weights are loaded afterwards)."""
    if pretrained:
        raise AssertionError("LPIPS backbone weights must come from eval.lpips_weights, never a download")
    try:
        from torchvision.models import vgg16

        return types.SimpleNamespace(features=vgg16(weights=None).features, source="torchvision")
    except Exception:  # noqa: BLE001 - torchvision absent or unloadable: the same layout, written out
        return types.SimpleNamespace(features=vgg16_features(), source="lightstage.training.lpips")


def import_lpips() -> types.ModuleType:
    """The `lpips` package; imported with a stand-in `torchvision.models` when torchvision cannot load."""
    if "lpips" in sys.modules and hasattr(sys.modules["lpips"], "LPIPS"):
        return sys.modules["lpips"]
    try:
        import lpips

        return lpips
    except ModuleNotFoundError as e:
        if e.name == "lpips":
            raise
        broken: Exception = e
    except (ImportError, RuntimeError, OSError) as e:  # torchvision built for another torch
        broken = e
    for name in [n for n in sys.modules if n.split(".")[0] in ("lpips", "torchvision")]:
        del sys.modules[name]  # the partial imports of the failed attempt
    tv = types.ModuleType("torchvision")
    tv.models = types.ModuleType("torchvision.models")  # type: ignore[attr-defined]
    tv.models.vgg16 = _backbone_architecture  # type: ignore[attr-defined]
    tv.__lightstage_stand_in__ = str(broken)  # type: ignore[attr-defined]
    sys.modules["torchvision"], sys.modules["torchvision.models"] = tv, tv.models  # type: ignore[attr-defined]
    try:
        import lpips
    finally:
        del sys.modules["torchvision"], sys.modules["torchvision.models"]
    return lpips


def _read_backbone(path: str) -> dict[str, torch.Tensor]:
    """The `features` tensors of a torchvision VGG16 state dict, keyed by layer index ("0.weight", ...)."""
    state = torch.load(path, map_location="cpu", weights_only=True)
    if isinstance(state, nn.Module):
        state = state.state_dict()
    if not isinstance(state, dict):
        raise ValueError(f"expected a state dict, got {type(state).__name__}")
    if any(str(k).startswith("features.") for k in state):
        return {k.removeprefix("features."): v for k, v in state.items() if k.startswith("features.")}
    return dict(state)


class LPIPSVGG(nn.Module):
    """`lpips.LPIPS(net="vgg", version="0.1")` with the given backbone tensors; forward(a, b) on [0, 1] RGB
    images (N, 3, H, W) -> (N,) distances."""

    def __init__(self, backbone: dict[str, torch.Tensor], linear_path: str | None = None):
        super().__init__()
        lp = import_lpips()
        pn = lp.pretrained_networks
        saved = pn.tv
        pn.tv = types.SimpleNamespace(vgg16=_backbone_architecture)  # the layout only; never a download
        try:
            self.net = lp.LPIPS(
                pretrained=True,
                net="vgg",
                version="0.1",
                pnet_rand=True,
                model_path=linear_path,
                verbose=False,
            )
        finally:
            pn.tv = saved
        slices = self.net.net  # lpips' vgg16: slice1..slice5 holding features[N] under the name "N"
        where = {
            name: f"slice{k}.{name}"
            for k in range(1, slices.N_slices + 1)
            for name, _ in getattr(slices, f"slice{k}").named_children()
        }
        unknown = sorted(set(k.split(".")[0] for k in backbone) - set(where))
        if unknown:
            raise ValueError(f"tensors for layers {unknown} that VGG16's features do not have")
        slices.load_state_dict(
            {f"{where[k.split('.')[0]]}.{k.split('.', 1)[1]}": v for k, v in backbone.items()}
        )
        self.eval().requires_grad_(False)

    @torch.no_grad()
    def forward(self, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        return self.net(a, b, normalize=True).reshape(-1)


def lpips_or_none(
    vgg_path: str, linear_path: str = "", device: str = "cpu"
) -> tuple[Callable[[np.ndarray, np.ndarray], float] | None, str]:
    """(fn(pred01 HxWx3, target01 HxWx3) -> float, note) when the VGG16 backbone weights exist locally, else
    (None, "unavailable: why"). `linear_path`: LPIPS linear layers ("" = the ones shipped in the package)."""
    if not vgg_path:
        return None, "unavailable: set eval.lpips_weights (a local torchvision VGG16 state dict, .pth)"
    for p in (vgg_path, linear_path):
        if p and not Path(p).is_file():
            return None, f"unavailable: {p} not found"
    try:
        import_lpips()
    except ModuleNotFoundError:
        return None, "unavailable: the lpips package is not installed (pip install lpips)"
    try:
        net = LPIPSVGG(_read_backbone(vgg_path), linear_path or None).to(device)
    except (OSError, RuntimeError, ValueError, KeyError, AttributeError, TypeError) as e:
        reason = " ".join(str(e).split())[:300] or type(e).__name__
        return None, f"unavailable: {vgg_path}: not a torchvision VGG16 state dict ({reason})"

    def fn(pred: np.ndarray, target: np.ndarray) -> float:
        t = [
            torch.from_numpy(np.ascontiguousarray(x, np.float32)).permute(2, 0, 1)[None].to(device)
            for x in (pred, target)
        ]
        return float(net(*t)[0])

    return (
        fn,
        f"lpips package, vgg v0.1 (linear layers {linear_path or 'shipped with the package'}), backbone {vgg_path}",
    )
