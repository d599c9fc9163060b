"""The hash encoding's fused CPU kernels (`lightstage.training.hashgrid_cpu`): the same features and table
gradients as the PyTorch path, independent of the thread count, and usable in a forked child."""

from __future__ import annotations

import multiprocessing

import pytest
import torch

from lightstage.training import hashgrid_cpu
from lightstage.training.hashgrid import HashGridEncoding

pytestmark = pytest.mark.skipif(not hashgrid_cpu.available(), reason="numba not installed")


def _points(n: int = 3000) -> torch.Tensor:
    gen = torch.Generator().manual_seed(3)
    x = torch.rand(n, 3, generator=gen) * 2.2 - 1.1  # some outside the cube: clamped to its faces
    x[:4] = torch.tensor([[1.0, 1.0, 1.0], [-1.0, -1.0, -1.0], [1.0, -1.0, 0.0], [0.0, 0.0, 0.0]])
    return x


def _run(enc: HashGridEncoding, x: torch.Tensor, fused: bool) -> tuple[torch.Tensor, torch.Tensor]:
    old = hashgrid_cpu.set_enabled(fused)
    try:
        enc.tables.grad = None
        out = enc(x)
        out.backward(torch.cos(torch.arange(out.numel(), dtype=torch.float32)).reshape(out.shape))
        return out.detach(), enc.tables.grad.clone()
    finally:
        hashgrid_cpu.set_enabled(old)


def test_fused_kernels_equal_the_pytorch_path():
    """`fast`'s layout (dense and hashed levels): features to float32 rounding, gradients too (the PyTorch
    path accumulates them in float64, the kernels in float32)."""
    torch.manual_seed(0)
    enc = HashGridEncoding(levels=16, features=2, log2_table_size=19, base_resolution=16, max_resolution=1024)
    with torch.no_grad():
        enc.tables.normal_()
    assert any(enc.dense) and not all(enc.dense)
    x = _points()
    out_f, grad_f = _run(enc, x, fused=True)
    out_t, grad_t = _run(enc, x, fused=False)
    torch.testing.assert_close(out_f, out_t, rtol=1e-6, atol=1e-6)
    torch.testing.assert_close(grad_f, grad_t, rtol=1e-5, atol=1e-6)
    assert grad_f.abs().sum() > 0


@pytest.mark.parametrize(
    ("features", "log2_table", "points"), [(2, 12, 5), (2, 12, 17), (1, 12, 3000), (4, 14, 3000), (3, 10, 7)]
)
def test_fused_kernels_equal_the_pytorch_path_at_other_widths_and_few_points(features, log2_table, points):
    """The generic loop (rows of other than 2 features) and the prefetch ring's edges (fewer points than it
    holds, or one more) give the PyTorch path's features and gradients too, on dense and hashed levels."""
    torch.manual_seed(1)
    enc = HashGridEncoding(8, features, log2_table, base_resolution=4, max_resolution=160)
    with torch.no_grad():
        enc.tables.normal_()
    assert any(enc.dense) and not all(enc.dense)
    x = _points(points)
    out_f, grad_f = _run(enc, x, fused=True)
    out_t, grad_t = _run(enc, x, fused=False)
    torch.testing.assert_close(out_f, out_t, rtol=1e-6, atol=1e-6)
    torch.testing.assert_close(grad_f, grad_t, rtol=1e-5, atol=1e-6)


def test_fused_kernels_do_not_depend_on_the_thread_count():
    """Each level belongs to one thread, so 1, 2 and 3 threads give bit-identical features and gradients."""
    enc = HashGridEncoding(levels=8, features=2, log2_table_size=12, base_resolution=4, max_resolution=128)
    with torch.no_grad():
        enc.tables.normal_()
    x = _points()
    threads = torch.get_num_threads()
    try:
        results = []
        for n in (1, 2, 3):
            torch.set_num_threads(n)
            results.append(_run(enc, x, fused=True))
    finally:
        torch.set_num_threads(threads)
    for out, grad in results[1:]:
        assert torch.equal(out, results[0][0]) and torch.equal(grad, results[0][1])


def _child(conn) -> None:
    enc = HashGridEncoding(levels=4, features=2, log2_table_size=10, base_resolution=4, max_resolution=32)
    conn.send(enc(torch.zeros(5, 3)).shape == (5, 8))


@pytest.mark.timeout(60)
def test_kernels_work_in_a_forked_child_after_the_parent_used_them():
    """The parent's worker threads do not survive a fork; the child starts its own pool instead of hanging."""
    torch.set_num_threads(max(2, torch.get_num_threads()))
    enc = HashGridEncoding(levels=4, features=2, log2_table_size=10, base_resolution=4, max_resolution=32)
    enc(torch.zeros(5, 3))  # the parent's pool is running
    ctx = multiprocessing.get_context("fork")
    parent, child = ctx.Pipe()
    proc = ctx.Process(target=_child, args=(child,))
    proc.start()
    ok = parent.poll(50) and parent.recv()
    proc.join(5)
    if proc.is_alive():
        proc.kill()
    assert ok and proc.exitcode == 0


def test_malloc_thresholds_apply_on_glibc():
    """Training keeps freed multi-MB blocks in the heap (`lightstage.malloc`); glibc accepts the settings."""
    import platform

    from lightstage.malloc import keep_large_blocks

    if platform.libc_ver()[0] != "glibc":
        pytest.skip("not glibc")
    assert keep_large_blocks() is True


def test_non_finite_positions_are_refused_not_read_out_of_bounds():
    """A NaN position would make an out-of-range row index; the kernels run without bounds checks."""
    enc = HashGridEncoding(levels=4, features=2, log2_table_size=10, base_resolution=4, max_resolution=32)
    x = torch.zeros(4, 3)
    x[2, 1] = float("nan")
    with pytest.raises(ValueError, match="non-finite"):
        enc(x)
    assert torch.isfinite(enc(torch.full((2, 3), float("inf")))).all()  # clamped onto the cube's face


def test_backward_kernel_zeroes_its_levels_first():
    """The table gradient's memory comes uninitialised (`torch.empty`): the kernel clears each level before
    it scatters, so leftovers in the buffer never reach the gradient."""
    import numpy as np

    enc = HashGridEncoding(levels=6, features=2, log2_table_size=12, base_resolution=4, max_resolution=96)
    u = ((_points(500) + 1.0) * 0.5).clamp(0.0, 1.0).numpy()
    go = np.cos(np.arange(6 * 2 * 500, dtype=np.float32)).reshape(6, 2, 500)
    clean = np.zeros(tuple(enc.tables.shape), np.float32)
    dirty = np.full(tuple(enc.tables.shape), np.nan, np.float32)
    for buf in (clean, dirty):
        hashgrid_cpu._run_by_level(hashgrid_cpu._backward_levels, 6, u, go, *enc._kernel_args, buf)
    np.testing.assert_array_equal(dirty, clean)
    assert np.abs(clean).sum() > 0


def _padded(enc: HashGridEncoding, packed: torch.Tensor) -> torch.Tensor:
    """The (levels, T, F) layout written before the tables were packed: each level's rows, then zeros."""
    out = torch.zeros(enc.levels, enc.table_size, enc.features)
    for level in range(enc.levels):
        out[level, : enc.sizes[level]] = packed[enc.offsets[level] : enc.offsets[level + 1]]
    return out


def test_tables_are_packed_and_padded_checkpoints_load_into_them():
    """Dense levels hold only their (res + 1)^3 rows; the initial values are the padded layout's draw; a state
    dict and Adam moments in the padded layout load packed, with the same lookups."""
    torch.manual_seed(5)
    enc = HashGridEncoding(6, 2, 12, base_resolution=4, max_resolution=96)
    torch.manual_seed(5)
    drawn = torch.empty(6, 2**12, 2).uniform_(-1e-4, 1e-4)
    assert enc.tables.shape == (sum(enc.sizes), 2) and sum(enc.sizes) < 6 * 2**12
    assert torch.equal(enc.tables.detach(), enc.packed(drawn))
    with torch.no_grad():
        enc.tables.normal_()
    old = {"tables": _padded(enc, enc.tables.detach())}
    fresh = HashGridEncoding(6, 2, 12, base_resolution=4, max_resolution=96)
    fresh.load_state_dict(old)
    assert torch.equal(fresh.tables, enc.tables)
    x = _points(300)
    assert torch.equal(fresh(x), enc(x))
    opt = torch.optim.Adam(fresh.parameters())
    moments = {"step": torch.tensor(3.0), "exp_avg": old["tables"] * 2, "exp_avg_sq": old["tables"] ** 2}
    opt.state[fresh.tables] = dict(moments)
    fresh.pack_optimizer_state(opt)
    state = opt.state[fresh.tables]
    assert torch.equal(state["exp_avg"], enc.tables.detach() * 2) and torch.equal(
        state["step"], moments["step"]
    )
    assert torch.equal(state["exp_avg_sq"], enc.tables.detach() ** 2)
