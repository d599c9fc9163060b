"""Envmap orientation, solid angles, area resampling and median cut (Debevec 2008) on synthetic maps."""

from __future__ import annotations

import numpy as np
import pytest

from lightstage.errors import LightstageError
from lightstage.training.envmap import (
    LUMINANCE,
    EnvMap,
    all_pixel_lights,
    load_envmap,
    median_cut,
    median_cut_regions,
    parse_resolution,
    pixel_directions,
    pixel_of_direction,
    resample,
    row_solid_angles,
)


def test_solid_angles_sum_to_sphere_and_follow_cos_latitude():
    for h, w in [(16, 32), (7, 13), (128, 256)]:
        omega = row_solid_angles(h, w)
        assert np.isclose(omega.sum() * w, 4 * np.pi, rtol=1e-12)
    omega = row_solid_angles(16, 32)
    lat = np.pi / 2 - np.pi * (np.arange(16) + 0.5) / 16
    ratio = omega / np.cos(lat)
    assert np.allclose(ratio, ratio[0], rtol=1e-12)  # exactly the cos(latitude) weighting


def test_orientation_top_is_zenith_centre_is_plus_x_left_is_plus_y():
    h, w = 16, 32
    d = pixel_directions(h, w)
    assert np.allclose(np.linalg.norm(d, axis=-1), 1.0)
    assert d[0, :, 2].min() > 0.99 and d[-1, :, 2].max() < -0.99
    # the equator pixel whose left edge is the centre line is just right of +x: longitude -pi/32
    assert np.allclose(
        pixel_directions(2, 4)[0, 1],
        [np.cos(np.pi / 4) * np.cos(np.pi / 4), np.cos(np.pi / 4) * np.sin(np.pi / 4), np.sin(np.pi / 4)],
    )
    assert pixel_of_direction([1, 0, 0], h, w) in [(7, 15), (7, 16), (8, 15), (8, 16)]
    assert pixel_of_direction([0, 1, 0.01], h, w) == (7, 8)  # left quarter
    assert pixel_of_direction([0, -1, 0.01], h, w) == (7, 24)  # right quarter
    assert pixel_of_direction([0.01, 0, 1], h, w)[0] == 0
    # rotation about +z by 90 deg carries longitude 0 (+x) to +y
    assert pixel_of_direction([0, 1, 0.01], h, w, rotate_deg=90.0) == pixel_of_direction([1, 0, 0.01], h, w)
    rng = np.random.default_rng(0)
    for _ in range(50):
        r, c = int(rng.integers(h)), int(rng.integers(w))
        for rot in (0.0, 33.0):
            assert pixel_of_direction(pixel_directions(h, w, rot)[r, c], h, w, rot) == (r, c)


def _map_bright_at(
    lat_deg: float, lon_deg: float, h: int = 64, w: int = 128, radius_deg: float = 8.0
) -> np.ndarray:
    d = pixel_directions(h, w)
    lat, lon = np.deg2rad(lat_deg), np.deg2rad(lon_deg)
    target = np.array([np.cos(lat) * np.cos(lon), np.cos(lat) * np.sin(lon), np.sin(lat)])
    near = d @ target > np.cos(np.deg2rad(radius_deg))
    img = np.full((h, w, 3), 1e-4)
    img[near] = 50.0
    return img


def test_map_bright_near_zenith_gives_a_light_near_plus_z():
    env = EnvMap(_map_bright_at(90.0, 0.0))
    one = median_cut(env, 1)
    assert one.directions[0, 2] > 0.999
    lights = median_cut(env, 8)
    k = int(np.argmax(lights.rgb @ LUMINANCE))
    total = lights.rgb.sum(axis=0)
    # the energy-weighted mean direction points up, every light sits in the bright cap
    mean = (lights.rgb @ LUMINANCE) @ lights.directions
    assert mean[2] / np.linalg.norm(mean) > 0.999
    assert lights.directions[k, 2] > 0.97
    assert np.allclose(total, env.energies().sum(axis=(0, 1)))


def test_map_bright_at_longitude_zero_gives_plus_x_and_rotates_to_plus_y():
    img = _map_bright_at(0.0, 0.0)
    d0 = median_cut(EnvMap(img), 1).directions[0]
    assert d0 @ np.array([1.0, 0, 0]) > 0.999
    d90 = median_cut(EnvMap(img, rotate_deg=90.0), 1).directions[0]
    assert d90 @ np.array([0, 1.0, 0]) > 0.999
    # a map bright at longitude +90 deg (left quarter of the image) is +y without rotation
    d = median_cut(EnvMap(_map_bright_at(0.0, 90.0)), 1).directions[0]
    assert d @ np.array([0, 1.0, 0]) > 0.999
    col = int(np.argmax(_map_bright_at(0.0, 90.0)[32, :, 0]))
    assert col < 64  # bright spot in the left half of the image


def test_uniform_map_gives_equal_energies_spread_by_solid_angle():
    h, w, k = 128, 256, 16
    env = EnvMap(np.ones((h, w, 3)))
    lights = median_cut(env, k)
    assert len(lights) == k
    e = lights.rgb[:, 1]
    assert np.isclose(e.sum(), 4 * np.pi)
    assert np.allclose(e, 4 * np.pi / k, rtol=0.03)
    # uniform radiance: energy = solid angle, so each light covers ~1/K of the sphere
    assert np.allclose(lights.solid_angles, 4 * np.pi / k, rtol=0.03)
    assert np.linalg.norm(lights.directions.mean(axis=0)) < 0.02  # spread evenly over the sphere
    assert np.sum(lights.directions[:, 2] > 0) == k // 2
    # lights are separated: nearest-neighbour angles are all similar and large
    cos = lights.directions @ lights.directions.T
    np.fill_diagonal(cos, -1)
    nearest = np.degrees(np.arccos(cos.max(axis=1)))
    assert nearest.min() > 20.0
    # at 32x16 the pixel grid limits equality but energies stay within 25 %
    small = median_cut(EnvMap(np.ones((16, 32, 3))), 16)
    assert np.allclose(small.rgb[:, 0], 4 * np.pi / 16, rtol=0.25)


def test_one_bright_pixel_gives_one_dominant_light_there_with_its_energy():
    h, w = 16, 32
    img = np.full((h, w, 3), 1e-3)
    r, c = 4, 21
    radiance = np.array([300.0, 200.0, 100.0])
    img[r, c] = radiance
    env = EnvMap(img)
    omega = row_solid_angles(h, w)[r]
    for k in (1, 4, 16, 64):
        lights = median_cut(env, k)
        lum = lights.rgb @ LUMINANCE
        top = int(np.argmax(lum))
        if k >= 16:
            assert lum[top] > 0.9 * lum.sum()
            assert np.degrees(np.arccos(min(1.0, lights.directions[top] @ env.directions()[r, c]))) < 3.0
            assert np.allclose(lights.rgb[top], radiance * omega, rtol=0.05)
    # with a black background the light sits exactly on the pixel and carries exactly L * Omega
    img0 = np.zeros((h, w, 3))
    img0[r, c] = radiance
    lights = median_cut(EnvMap(img0), 16).nonzero()
    assert len(lights) == 1
    assert np.allclose(lights.directions[0], pixel_directions(h, w)[r, c], atol=1e-12)
    assert np.allclose(lights.rgb[0], radiance * omega, rtol=1e-12)


def test_median_cut_regions_tile_the_map_and_balance_energy():
    rng = np.random.default_rng(1)
    img = rng.gamma(0.5, 1.0, size=(16, 32, 3))
    env = EnvMap(img)
    for k in (2, 8, 32, 512):
        regions = median_cut_regions(env, k)
        cover = np.zeros((16, 32), int)
        for reg in regions:
            cover[reg.row0 : reg.row1, reg.col0 : reg.col1] += 1
        assert np.all(cover == 1)
        assert len(regions) == k
    lights = median_cut(env, 32)
    assert np.allclose(lights.rgb.sum(axis=0), env.energies().sum(axis=(0, 1)))
    allp = all_pixel_lights(env)
    assert len(allp) == 512 and np.allclose(allp.rgb.sum(axis=0), lights.rgb.sum(axis=0))


def test_median_cut_rejects_bad_counts():
    env = EnvMap(np.ones((16, 32, 3)))
    with pytest.raises(LightstageError, match="power of two"):
        median_cut(env, 12)
    with pytest.raises(LightstageError, match="pixels"):
        median_cut(env, 1024)


def test_resample_preserves_energy_and_uniform_maps():
    rng = np.random.default_rng(2)
    big = rng.gamma(0.7, 2.0, size=(128, 256, 3)).astype(np.float32)
    small = resample(big, 32, 16)
    e_big = (big * row_solid_angles(128, 256)[:, None, None]).sum(axis=(0, 1))
    e_small = (small * row_solid_angles(16, 32)[:, None, None]).sum(axis=(0, 1))
    assert np.allclose(e_big, e_small, rtol=1e-5)
    assert np.allclose(resample(np.full((100, 200, 3), 2.5, np.float32), 32, 16), 2.5, rtol=1e-5)


def test_load_envmap_exr_and_hdr(tmp_path):
    from lightstage.frames import write_exr, write_image

    img = np.random.default_rng(3).uniform(0, 10, size=(64, 128, 3)).astype(np.float32)
    write_exr(tmp_path / "m.exr", img, half=False)
    env = load_envmap(tmp_path / "m.exr", (32, 16), rotate_deg=10.0)
    assert env.radiance.shape == (16, 32, 3) and env.rotate_deg == 10.0
    assert np.allclose(
        env.energies().sum(axis=(0, 1)),
        (img * row_solid_angles(64, 128)[:, None, None]).sum(axis=(0, 1)),
        rtol=1e-5,
    )
    write_image(tmp_path / "m.hdr", img)
    env2 = load_envmap(tmp_path / "m.hdr", None)
    assert env2.radiance.shape == (64, 128, 3)
    assert np.allclose(env2.radiance, img, rtol=0, atol=0.1)  # RGBE: 8-bit mantissa shared by RGB
    bad = img.copy()
    bad[3, 3, 1] = np.nan
    write_exr(tmp_path / "bad.exr", bad, half=False)
    with pytest.raises(LightstageError, match="non-finite"):
        load_envmap(tmp_path / "bad.exr")
    with pytest.raises(LightstageError, match="not found"):
        load_envmap(tmp_path / "missing.exr")
    assert parse_resolution("64x32") == (64, 32)
    with pytest.raises(LightstageError):
        parse_resolution("64")


def test_real_envmaps_load_and_cut(shared_data):
    for name in ("KernerEnvLatLong.exr", "StageEnvLatLong.exr"):
        env = load_envmap(shared_data / "envmaps" / name)
        assert env.radiance.shape == (16, 32, 3) and np.all(np.isfinite(env.radiance))
        lights = median_cut(env, 64)
        assert len(lights) == 64
        assert np.allclose(lights.rgb.sum(axis=0), env.energies().sum(axis=(0, 1)))
