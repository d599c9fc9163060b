"""Compact shards (16 bytes a ray): rays recomputed from the manifest's camera and light tables equal, bit for
bit, the float32 rays the 64-byte format stored (`view_rays`, the camera model); flags keep saturated, zone and
flare bits; old-format shards are refused naming the command that rebuilds them; training on rays recomputed at
load time gives the same model as training on the stored rays, at equal seeds."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
import torch
from support.fixtures import make_synthetic_work
from support.training import micro_config

from lightstage.cameras import look_at
from lightstage.dataset.loader import RayShardDataset
from lightstage.dataset.ray_table import RayTable
from lightstage.dataset.shard_config import ShardConfig
from lightstage.dataset.shard_rays import view_rays
from lightstage.dataset.shards import run_shard
from lightstage.dataset.split import SplitConfig, run_split
from lightstage.errors import LightstageError
from lightstage.records.shards import (
    FLAG_FLARE,
    RAY_DTYPE,
    flags_flare,
    flags_saturated,
    flags_zone,
    load_manifest,
    pack_flags,
)
from lightstage.training.inputs import ShardSource


def _camera_table(seed: int, n_views: int, distorted: bool) -> dict:
    rng = np.random.default_rng(seed)
    cams, views = [], []
    for k in range(n_views):
        pos = rng.normal(size=3)
        R, t = look_at(1.8 * pos / np.linalg.norm(pos), rng.normal(scale=0.05, size=3))
        f = rng.uniform(1500, 2200)
        K = [
            [f, rng.uniform(-1, 1), rng.uniform(1000, 1050)],
            [0.0, f * 1.001, rng.uniform(660, 700)],
            [0, 0, 1],
        ]
        dist = (
            [-0.12, 0.05, 0.001, -0.002, 0.01] * rng.uniform(0.5, 1.5, 5)
            if distorted and k % 2
            else [0.0] * 5
        )
        cams.append(
            {"K": K, "R": R.tolist(), "t": t.tolist(), "dist": list(dist), "width": 2048, "height": 1366}
        )
        views.append(f"{40 * (k % 3):03d}/cam{k:02d}")
    lights = {}
    for g in sorted({v.split("/")[0] for v in views}):
        p = rng.normal(size=(331, 3))
        p *= 1.5 / np.linalg.norm(p, axis=1, keepdims=True)
        d = p - 0.01
        lights[g] = {
            "positions": p.tolist(),
            "directions": (d / np.linalg.norm(d, axis=1, keepdims=True)).tolist(),
        }
    return {"views": views, "cameras": cams, "lights": lights}


@pytest.mark.parametrize("distorted", [False, True])
def test_rays_equal_the_stored_float32_rays_bit_for_bit(distorted):
    m = _camera_table(3, 6, distorted)
    rng = np.random.default_rng(1)
    n = 120_000
    view = rng.integers(0, 6, n)
    light = rng.integers(0, 331, n)
    pixel = np.stack([rng.integers(-360, 2048 + 360, n), rng.integers(-360, 1366 + 360, n)], 1)
    o, d, lp, ld = (x.numpy() for x in RayTable(m).rays(*(torch.from_numpy(a) for a in (view, light, pixel))))
    for v in range(6):
        c = m["cameras"][v]
        at = view == v
        ro, rd = view_rays(*(np.array(c[k], np.float64) for k in ("K", "R", "t", "dist")), pixel[at])
        np.testing.assert_array_equal(o[at], ro)
        np.testing.assert_array_equal(d[at], rd)
        g = m["views"][v].split("/")[0]
        np.testing.assert_array_equal(
            lp[at], np.array(m["lights"][g]["positions"])[light[at]].astype(np.float32)
        )
        np.testing.assert_array_equal(
            ld[at], np.array(m["lights"][g]["directions"])[light[at]].astype(np.float32)
        )


def test_flags_round_trip_with_spare_bits():
    sat = np.array([0, 1, 0, 1], bool)
    zone = np.array([2, 1, 0, 2], np.uint8)
    f = pack_flags(sat, zone, flare=np.array([0, 0, 1, 1], bool))
    assert f.dtype == np.uint16 and RAY_DTYPE.itemsize == 16 and RAY_DTYPE["flags"] == np.dtype("<u2")
    np.testing.assert_array_equal(flags_saturated(f), sat)
    np.testing.assert_array_equal(flags_zone(f), zone)
    np.testing.assert_array_equal(flags_flare(f), [False, False, True, True])
    assert not (f & ~np.uint16(0b1111)).any() and FLAG_FLARE == 8  # bits 4-15 spare
    t = torch.from_numpy(f.view(np.int16))
    assert flags_zone(t).tolist() == zone.tolist() and flags_saturated(t).tolist() == sat.tolist()


@pytest.fixture(scope="module")
def sharded(tmp_path_factory):
    work, _ = make_synthetic_work(tmp_path_factory.mktemp("compact"))
    run_split(work, SplitConfig("paper"), progress=False)
    run_shard(work, ShardConfig(rays_per_image=64, rays_per_shard=256, workers=1), progress=False)
    return work


def test_old_format_is_refused_naming_the_rebuild(sharded, tmp_path):
    copy = tmp_path / "work"
    shutil.copytree(sharded.root, copy)
    path = copy / "shards" / "manifest.json"
    m = json.loads(path.read_text())
    path.write_text(json.dumps(m | {"format_version": 1}))
    with pytest.raises(LightstageError, match=r"old format 1 .*rerun `lightstage shard .*work --force`"):
        RayShardDataset(copy / "shards", batch_size=64)
    # a plain rerun of the shard stage (same inputs and config) rewrites them in the current format
    from lightstage.workdir import WorkDir

    cfg = ShardConfig(rays_per_image=64, rays_per_shard=256, workers=1)
    assert not run_shard(WorkDir.at(copy), cfg, progress=False)["skipped"]
    assert load_manifest(copy / "shards")["shards"] == load_manifest(sharded.shards_dir)["shards"]


class StoredRays:
    """The 64-byte format's source: the same compact batches, their rays as the old shard stage stored them
    (numpy `view_rays`, float32), handed to the trainer as stored rays."""

    def __init__(self, source: ShardSource):
        self.source = source
        self.m = load_manifest(source.work.shards_dir)

    def batches(self, start: int = 0, rank: int = 0, world_size: int = 1):
        ds = self.source.dataset(rank, world_size)
        for compact in ds.batches(start):
            r = compact["records"].numpy().view(RAY_DTYPE).reshape(-1)
            o = np.zeros((len(r), 3), np.float32)
            d = np.zeros((len(r), 3), np.float32)
            lp, ld = np.zeros_like(o), np.zeros_like(o)
            for v in np.unique(r["view"]):
                c, at = self.m["cameras"][v], r["view"] == v
                K, R, t, dist = (np.array(c[k], np.float64) for k in ("K", "R", "t", "dist"))
                o[at], d[at] = view_rays(K, R, t, dist, r["pixel"][at].astype(np.int64))
                g = self.m["lights"][self.m["views"][v].split("/")[0]]
                lp[at] = np.array(g["positions"])[r["light"][at]]
                ld[at] = np.array(g["directions"])[r["light"][at]]
            yield {
                "origins": torch.from_numpy(o),
                "directions": torch.from_numpy(d),
                "light_positions": torch.from_numpy(lp),
                "light_directions": torch.from_numpy(ld),
                "rgb": torch.from_numpy(r["rgb"].astype(np.float32)),
                "saturated": torch.from_numpy(flags_saturated(r["flags"])),
                "zone": torch.from_numpy(flags_zone(r["flags"])),
                "flare": torch.from_numpy(flags_flare(r["flags"])),
            }


def test_training_on_recomputed_rays_equals_training_on_stored_rays(sharded, tmp_path):
    from lightstage.training.trainer import fit

    source = ShardSource(sharded, 64, seed=0)
    a, b = next(source.batches(3)), next(StoredRays(source).batches(3))
    for k in a:
        assert torch.equal(a[k], b[k]), k
    norm = source.normalization()
    params = []
    for name, src in (("recomputed", source), ("stored", StoredRays(source))):
        live: list = []
        cfg = micro_config(steps=3)
        fit(
            cfg,
            src,
            tmp_path / name,
            norm["centre"],
            norm["scale"],
            device="cpu",
            progress=False,
            model_out=live,
        )
        params.append(live[0].state_dict())
    assert params[0].keys() == params[1].keys()
    for k in params[0]:
        assert torch.equal(params[0][k], params[1][k]), k
