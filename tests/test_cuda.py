"""What only a GPU exercises (skipped without CUDA; `bench/gpu_check.sh` runs this file first on a device).
Both cases broke the first GPU run of 2026-12-04: CUDA has no integer matmul, and a checkpoint loaded onto the GPU
holds its RNG states there, which torch refuses to restore."""

from __future__ import annotations

import io

import pytest
import torch

from lightstage.training.checkpoint import rng_state, set_rng_state
from lightstage.training.hashgrid import HashGridEncoding

cuda = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")


@cuda
def test_hash_grid_on_cuda_equals_cpu():
    """Dense and hashed levels alike: the same features on both devices, gradients too."""
    torch.manual_seed(0)
    enc = HashGridEncoding(levels=6, features=2, log2_table_size=12, base_resolution=4, max_resolution=64)
    x = torch.rand(1000, 3) * 2 - 1
    out_cpu = enc(x)
    out_cpu.square().sum().backward()
    grad_cpu = enc.tables.grad.clone()
    enc.tables.grad = None
    enc = enc.cuda()
    out_gpu = enc(x.cuda())
    out_gpu.square().sum().backward()
    torch.testing.assert_close(out_gpu.cpu(), out_cpu, rtol=1e-5, atol=1e-7)
    torch.testing.assert_close(enc.tables.grad.cpu(), grad_cpu, rtol=1e-4, atol=1e-8)


@cuda
def test_rng_state_restores_from_a_checkpoint_loaded_onto_the_gpu():
    """A resume loads the checkpoint with map_location=cuda; the RNG sequences must continue exactly."""
    torch.manual_seed(1)
    buffer = io.BytesIO()
    torch.save(rng_state(), buffer)
    expected = (torch.rand(4), torch.rand(4, device="cuda").cpu())
    buffer.seek(0)
    state = torch.load(buffer, map_location="cuda", weights_only=True)
    set_rng_state(state)
    torch.testing.assert_close((torch.rand(4), torch.rand(4, device="cuda").cpu()), expected)
