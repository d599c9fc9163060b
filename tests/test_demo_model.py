"""The demo's model (the `cpu` config) on a simulated capture, through the real stages: it must beat the
constant-colour baseline on the masked metric by a wide margin and stay below the ceiling."""

from __future__ import annotations

import pytest


@pytest.mark.slow
def test_cpu_model_beats_the_baseline_on_the_masked_metric(tiny_model_eval):
    _, mean = tiny_model_eval  # support.training.train_and_eval on the tiny capture
    assert mean["psnr"] >= mean["baseline_psnr"] + 8.0, mean
    assert mean["psnr"] < mean["ceiling_psnr"], mean
