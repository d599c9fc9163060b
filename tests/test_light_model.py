"""Point lights at a finite distance (`model.light: point`): the light frame recovered from light positions and
directions, per-sample directions and inverse-square falloff, and the model that stores the frame."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from support.synthetic import SyntheticSphere

from lightstage.training.config import load_config
from lightstage.training.light_model import light_frame, point_light
from lightstage.training.model import RelightModel
from lightstage.training.trainer import measure_light_frame


def test_light_frame_recovers_centre_and_radius():
    rng = np.random.default_rng(0)
    w = rng.normal(size=(30, 3))
    w /= np.linalg.norm(w, axis=1, keepdims=True)
    centre = np.array([0.01, -0.02, 0.1])
    c, r = light_frame(centre + 1.5 * w, w)
    np.testing.assert_allclose(c, centre, atol=1e-9)
    assert r == pytest.approx(1.5)
    with pytest.raises(ValueError):  # one direction only: the centre could be anywhere on the line
        light_frame(np.array([[0, 0, 1.0], [0, 0, 2.0]]), np.array([[0, 0, 1.0], [0, 0, 1.0]]))


def test_point_light_direction_and_inverse_square_falloff():
    x = torch.tensor([[0.0, 0.0, 0.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])
    dirs, fall = point_light(x, torch.tensor([0.0, 0.0, 2.0]), 2.0)
    torch.testing.assert_close(dirs[:2], torch.tensor([[0.0, 0.0, 1.0]] * 2))
    torch.testing.assert_close(dirs[2], torch.tensor([-1.0, 0.0, 2.0]) / 5**0.5)
    torch.testing.assert_close(fall, torch.tensor([1.0, 4.0, 4.0 / 5.0]))


def test_point_model_measures_its_lights_and_keeps_them_in_the_state_dict():
    src = SyntheticSphere(batch_size=64)
    centre, radius = measure_light_frame(src, 2)  # the sphere's lights: centre + 1.5 * direction
    np.testing.assert_allclose(centre, src.centre, atol=1e-5)
    assert radius == pytest.approx(1.5, rel=1e-5)
    cfg = load_config("cpu", {"model": {"light": "point"}}).model
    model = RelightModel(cfg, src.centre, src.scale)
    model.set_light_frame(centre, radius)
    b = src.batch(0)
    out = model(b["origins"], b["directions"], b["light_directions"], randomized=True)
    out["rgb"].sum().backward()
    assert torch.isfinite(out["rgb"]).all() and model.fine.head[0].weight.grad.abs().sum() > 0
    again = RelightModel(cfg, src.centre, src.scale)
    again.load_state_dict(model.state_dict())
    assert float(again.light_radius) == pytest.approx(1.5, rel=1e-5)
    with torch.no_grad():
        model.eval(), again.eval()
        a = model(b["origins"], b["directions"], b["light_directions"])["rgb"]
        torch.testing.assert_close(a, again(b["origins"], b["directions"], b["light_directions"])["rgb"])


def test_a_far_point_light_renders_like_a_distant_one():
    src = SyntheticSphere(batch_size=64)
    torch.manual_seed(0)
    distant = RelightModel(load_config("cpu").model, src.centre, src.scale)
    point = RelightModel(load_config("cpu", {"model": {"light": "point"}}).model, src.centre, src.scale)
    point.load_state_dict(
        {**distant.state_dict(), **{k: v for k, v in point.state_dict().items() if "light_" in k}}
    )
    point.set_light_frame(src.centre, 1e6)
    b = src.batch(0)
    with torch.no_grad():
        want = distant.eval()(b["origins"], b["directions"], b["light_directions"])["rgb"]
        got = point.eval()(b["origins"], b["directions"], b["light_directions"])["rgb"]
    torch.testing.assert_close(got, want, rtol=1e-4, atol=1e-6)
