"""`decoder: auto` (issue 24): each worker process times both raw decoders on its first frames and keeps the
cheaper; the choice follows the measurements, not the machine's name. One banded decode serves several factors."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from lightstage.frames import write_exr
from lightstage.preprocess.decoder_choice import PROBE_FRAMES, DecoderChooser, choose, next_to_probe
from lightstage.preprocess.downscale import decode_downscale_factors, decode_raw, downscale


def _chooser_with_costs(costs: dict[str, float]) -> tuple[DecoderChooser, list[str]]:
    """A chooser whose clock advances by each decoder's cost while it decodes; `ran` gets "chosen" where the
    chooser releases the probe's freed memory."""
    now = [0.0]
    ran: list[str] = []

    def decode(decoder: str) -> str:
        ran.append(decoder)
        now[0] += costs[decoder]
        return decoder

    chooser = DecoderChooser(clock=lambda: now[0], on_chosen=lambda: ran.append("chosen"))
    chooser.decode = decode  # type: ignore[attr-defined]
    return chooser, ran


@pytest.mark.parametrize("cheaper", ["openexr", "bands"])
def test_auto_times_each_decoder_in_a_run_then_keeps_the_cheaper(cheaper: str) -> None:
    costs = {"openexr": 1.0, "bands": 1.0}
    costs[cheaper] = 0.6
    chooser, ran = _chooser_with_costs(costs)
    for _ in range(12):
        result, used = chooser.run("auto", chooser.decode)  # type: ignore[attr-defined]
        assert result == used
    probing = 2 * (PROBE_FRAMES + 1)
    # one run of consecutive frames per decoder: a whole-frame decode is timed reusing its own freed block;
    # then, once, the probe's freed blocks are given back (a worker keeping the bands would hold a whole frame)
    assert ran[: probing + 1] == ["openexr"] * (PROBE_FRAMES + 1) + ["bands"] * (PROBE_FRAMES + 1) + [
        "chosen"
    ]
    assert chooser.chosen == cheaper and set(ran[probing + 1 :]) == {cheaper}
    assert chooser.counts == {d: ran.count(d) for d in ("openexr", "bands")}
    assert chooser.probe_medians() == {d: pytest.approx(costs[d]) for d in costs}


def test_configured_decoder_is_used_without_probing() -> None:
    chooser, ran = _chooser_with_costs({"openexr": 5.0, "bands": 1.0})
    for _ in range(6):
        chooser.run("openexr", chooser.decode)  # type: ignore[attr-defined]
    assert ran == ["openexr"] * 6 and chooser.chosen is None and chooser.probe_medians() == {}


def test_choose_ignores_first_samples_and_waits_for_enough() -> None:
    assert choose({"openexr": [9.0, 1.0, 1.0], "bands": [0.1, 2.0]}) is None  # bands: one counted sample
    assert (
        choose({"openexr": [9.0, 1.0, 1.0], "bands": [0.1, 2.0, 2.0]}) == "openexr"
    )  # first samples left out
    assert choose({"openexr": [0, 1.0, 1.0], "bands": [0, 1.0, 1.0]}) == "openexr"  # a tie: the first decoder
    assert next_to_probe({"openexr": [1.0], "bands": []}) == "openexr"  # its run is not finished
    assert next_to_probe({"openexr": [1.0] * (PROBE_FRAMES + 1), "bands": []}) == "bands"


def test_one_banded_decode_gives_every_factor_exactly(tmp_path: Path) -> None:
    rng = np.random.default_rng(3)
    rgb = (rng.random((48, 64, 3)) * 5.0).astype(np.float16)  # some samples above the cutoff
    path = tmp_path / "raw.exr"
    write_exr(path, rgb, half=True)
    outs = decode_downscale_factors(path, (64, 48), 4.4, band_rows=24, factors=(4, 2))
    whole = np.asarray(decode_raw(path, (64, 48)))
    for out, f in zip(outs, (4, 2), strict=True):
        ref = downscale(whole, 4.4, factor=f)
        np.testing.assert_array_equal(out.rgb, ref.rgb)
        np.testing.assert_array_equal(out.saturated, ref.saturated)
    assert outs[0].saturated.any()


def test_config_rejects_an_unknown_decoder_naming_every_choice():
    """`decoder` is checked against decoder_choice.CHOICES, and the message lists them."""
    from lightstage.config import ConfigError
    from lightstage.preprocess.config import PreprocessConfig
    from lightstage.preprocess.decoder_choice import CHOICES

    for name in CHOICES:
        assert PreprocessConfig(decoder=name).decoder == name
    with pytest.raises(ConfigError, match="decoder") as err:
        PreprocessConfig.from_dict({"decoder": "openexr-bands"})
    assert all(name in str(err.value) for name in CHOICES)
