"""The simulator's fast paths give the bits of the plain numpy they replace (frames stay byte-identical)."""

from __future__ import annotations

import numpy as np
import pytest

from lightstage.records.processed import to_half
from lightstage.simulator import render
from lightstage.simulator.render import add_noise_and_clip
from lightstage.simulator.scene import default_scene
from lightstage.simulator.shading import _union_normal, ellipsoid_normal, scatter_rows


def test_to_half_rounds_like_numpy() -> None:
    rng = np.random.default_rng(0)
    bits = rng.integers(0, 0x7F800000, 300_000, dtype=np.uint32)  # every finite magnitude, denormals included
    x = bits.view(np.float32)
    x = np.concatenate([x, -x, np.float32([0.0, -0.0, 65504, 65519, 65520, 2.98e-8, 5.96e-8])])
    for arr in (x, x[: len(x) // 3 * 3].reshape(-1, 1, 3), x[:6000].reshape(20, 100, 3)):
        with np.errstate(over="ignore"):  # beyond the half range: inf, both ways
            assert np.array_equal(to_half(arr).view(np.uint16), arr.astype(np.float16).view(np.uint16))
    wide = rng.normal(size=(4, 5, 3))  # float64: numpy's direct rounding, not via float32
    assert np.array_equal(to_half(wide).view(np.uint16), wide.astype(np.float16).view(np.uint16))


@pytest.mark.parametrize("realism", ["stage", "clean"])
def test_noise_bands_do_not_change_the_bits(realism: str, monkeypatch: pytest.MonkeyPatch) -> None:
    scene = default_scene(texture_seed=0, realism=realism)
    rng = np.random.default_rng(1)
    img = (np.exp(rng.normal(-3, 2.5, (37, 29, 3))) * (rng.random((37, 29, 3)) > 0.1)).astype(np.float32)
    img[0, 0] = [4.4019, 5.0, 500.0]
    normal = rng.standard_normal(img.size, dtype=np.float32)
    monkeypatch.setattr(render, "NOISE_BAND_VALUES", 1 << 30)  # one band: the whole frame
    whole = add_noise_and_clip(img, scene, 4.4019, normal)
    monkeypatch.setattr(render, "NOISE_BAND_VALUES", 200)  # bands of 2 rows, a shorter last one
    banded = add_noise_and_clip(img, scene, 4.4019, normal)
    assert banded.dtype == np.float16 and np.array_equal(banded.view(np.uint16), whole.view(np.uint16))
    assert (whole[0, 0] >= np.float16(4.4019)).all()


def test_scatter_rows_is_fancy_assignment() -> None:
    rng = np.random.default_rng(2)
    dst = rng.random((50, 3), dtype=np.float32)
    ref = dst.copy()
    index = rng.choice(50, 20, replace=False)
    rows = rng.random((20, 3), dtype=np.float32)
    rows[0] = [-0.0, np.nan, np.inf]
    ref[index] = rows
    scatter_rows(dst, index, rows)
    assert np.array_equal(dst.view(np.uint32), ref.view(np.uint32))


def test_union_normal_is_the_nearest_ellipsoids_normal() -> None:
    scene = default_scene(texture_seed=0)
    rng = np.random.default_rng(3)
    p = tuple((rng.normal(0, 0.06, 5000)).astype(np.float32) for _ in range(3))
    errs = []
    for e in scene.body:
        q = [(p[i] - e.centre[i]) / e.radii[i] for i in range(3)]
        errs.append(np.abs(np.sqrt(q[0] ** 2 + q[1] ** 2 + q[2] ** 2) - 1.0))
    nearest = np.argmin(np.stack(errs), axis=0)
    normals = np.stack([np.stack(ellipsoid_normal(e, p)) for e in scene.body])  # (K, 3, N)
    expect = normals[nearest, :, np.arange(len(nearest))].T
    got = np.stack(_union_normal(scene, p))
    assert np.array_equal(got.view(np.uint32), expect.view(np.uint32))
