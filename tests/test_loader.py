"""The streaming loader: batch composition, rank x worker partition of an epoch, resume, corruption."""

from __future__ import annotations

import shutil

import numpy as np
import pytest
import torch
from support.fixtures import make_synthetic_work

from lightstage.dataset.loader import RayLoader, RayShardDataset
from lightstage.dataset.ray_table import RayTable
from lightstage.dataset.shard_config import ShardConfig
from lightstage.dataset.shards import run_shard
from lightstage.dataset.split import SplitConfig, run_split
from lightstage.errors import LightstageError
from lightstage.records.shards import BATCH_KEYS, load_manifest
from lightstage.workdir import ZONE_BACKGROUND, ZONE_BAND, ZONE_FOREGROUND

B = 64


@pytest.fixture(scope="module")
def shards(tmp_path_factory):
    root = tmp_path_factory.mktemp("loader")
    work, _ = make_synthetic_work(root)
    run_split(work, SplitConfig("paper"), progress=False)
    # 18 images x 64 rays in 3 shards of 384 = 6 whole batches of B each (the partition test relies on it)
    run_shard(work, ShardConfig(rays_per_image=64, rays_per_shard=384, workers=1), progress=False)
    return work.shards_dir


def _keys(batch: dict[str, torch.Tensor]) -> list[bytes]:
    """One identity per ray: its origin, direction and light direction bytes."""
    x = torch.cat([batch["origins"], batch["directions"], batch["light_directions"]], dim=1).numpy()
    return [row.tobytes() for row in x]


def _all_shard_keys(shards_dir) -> list[bytes]:
    m = load_manifest(shards_dir)
    table = RayTable(m)
    out = []
    for s in m["shards"]:
        a = np.load(shards_dir / s["file"])
        out += _keys(table.expand(torch.from_numpy(a.view(np.int16).reshape(len(a), 8))))
    return out


def test_batch_dict_and_composition(shards):
    ds = RayShardDataset(shards, batch_size=B)
    n = 0
    for batch in ds:
        assert set(batch) == set(BATCH_KEYS)
        for k in ("origins", "directions", "light_positions", "light_directions", "rgb"):
            assert batch[k].shape == (B, 3) and batch[k].dtype == torch.float32
        assert batch["saturated"].dtype == torch.bool and batch["saturated"].shape == (B,)
        z = batch["zone"]
        assert z.dtype == torch.uint8 and z.shape == (B,)
        assert int((z == ZONE_FOREGROUND).sum()) == B // 2
        assert int((z == ZONE_BAND).sum()) == 3 * B // 8
        assert int((z == ZONE_BACKGROUND).sum()) == B // 8
        assert torch.allclose(batch["directions"].norm(dim=1), torch.ones(B), atol=1e-5)
        n += 1
    assert n == len(ds) == ds.total_batches
    assert ds.state_dict()["epoch"] == 1 and ds.state_dict()["position"] == 0


def test_ranks_and_workers_partition_the_epoch(shards):
    everything = _all_shard_keys(shards)
    ranks = []
    for rank in range(2):
        ds = RayShardDataset(shards, batch_size=B, rank=rank, world_size=2, seed=3)
        ranks.append([k for b in RayLoader(ds, num_workers=2) for k in _keys(b)])
    assert len(ranks[0]) == len(ranks[1])  # DDP ranks step in lockstep
    seen = ranks[0] + ranks[1]
    assert len(seen) == len(set(seen))  # disjoint: no ray twice in an epoch
    assert set(seen) == set(everything)  # the shards here are whole batches: the epoch covers every ray
    # worker split inside one rank is disjoint too, and the DataLoader order is the single-process order
    ds1 = RayShardDataset(shards, batch_size=B, rank=1, world_size=2, seed=3)
    assert [k for b in ds1 for k in _keys(b)] == ranks[1]


def test_epochs_reshuffle(shards):
    ds = RayShardDataset(shards, batch_size=B)
    e0 = [k for b in ds for k in _keys(b)]
    e1 = [k for b in ds for k in _keys(b)]
    assert set(e0) == set(e1) and e0 != e1


def test_resume_at_position(shards):
    ref_ds = RayShardDataset(shards, batch_size=B, seed=5)
    ref = [_keys(b) for b in ref_ds] + [_keys(b) for b in ref_ds]  # two epochs
    ds = RayShardDataset(shards, batch_size=B, seed=5)
    loader = RayLoader(ds, num_workers=2)
    got = []
    for i, b in enumerate(loader):
        got.append(_keys(b))
        if i == 4:
            break
    state = loader.state_dict()
    assert state["epoch"] == 0 and state["position"] == 5
    ds2 = RayShardDataset(shards, batch_size=B, seed=5)
    loader2 = RayLoader(ds2, num_workers=2)
    loader2.load_state_dict(state)
    got += [_keys(b) for b in loader2]
    assert loader2.state_dict() == {**state, "epoch": 1, "position": 0}
    got += [_keys(b) for b in loader2]
    assert got == ref
    # the endless stream of the trainer's BatchSource protocol restarts at a step count
    ds3 = RayShardDataset(shards, batch_size=B, seed=5)
    stream = ds3.batches(start=len(ds3) + 3)
    assert _keys(next(stream)) == ref[len(ds3) + 3]
    with pytest.raises(LightstageError, match="position"):
        ds3.load_state_dict({"epoch": 0, "position": 10_000})


def test_normalized_coordinates(shards):
    a = next(iter(RayShardDataset(shards, batch_size=B, shuffle=False)))
    ds = RayShardDataset(shards, batch_size=B, shuffle=False, normalize=True)
    b = next(iter(ds))
    c = torch.tensor(ds.normalization["centre"], dtype=torch.float32)
    s = ds.normalization["scale"]
    torch.testing.assert_close(b["origins"], (a["origins"] - c) / s)
    torch.testing.assert_close(b["directions"], a["directions"])


def test_corrupted_shard_is_detected(shards, tmp_path):
    copy = tmp_path / "shards"
    shutil.copytree(shards, copy)
    m = load_manifest(copy)
    path = copy / m["shards"][0]["file"]
    data = bytearray(path.read_bytes())
    data[200] ^= 0x10
    path.write_bytes(bytes(data))
    with pytest.raises(LightstageError, match="checksum mismatch"):
        for _ in RayShardDataset(copy, batch_size=B, shuffle=False):
            pass
    with pytest.raises(LightstageError, match="checksum mismatch"):
        RayShardDataset(copy, batch_size=B, verify="all")
    with pytest.raises(LightstageError, match="multiple of 8"):
        RayShardDataset(shards, batch_size=60)
