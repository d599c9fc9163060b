"""The hash encoding's CPU kernels: lookup and its table gradient fused per level in numba, so no (8, levels, N)
index or weight array is materialised and the gradient is scattered straight into a float32 table.

The arithmetic is `HashGridEncoding`'s (float32 positions, the int32-exact spatial hash, the same corner order);
the PyTorch path stays for CUDA and as the reference. Work is split by level over a small thread pool of
GIL-free calls: each level is one thread's alone, so the scatter needs no atomics, and results do not depend
on the thread count. Numba's own parallel layers are avoided on purpose (the `omp` one is not fork-safe with
GNU OpenMP, `workqueue` not thread-safe).
"""

from __future__ import annotations

import os
import threading
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import torch

try:
    import numba
    from llvmlite import ir
    from numba.core import cgutils, types
    from numba.extending import intrinsic
except ImportError:  # pragma: no cover - numba is a dependency; the PyTorch path still works without it
    numba = None

# Points ahead whose corner rows are prefetched: the rows of the hashed levels are random reads into 4 MB
# tables, so without it a point waits on its own misses (forward 12.4 -> 8.1 ms for `fast`'s 44 k samples on
# the AMD EPYC VM, cold caches; 8-32 all within noise of 16; docs/benchmarks.md)
PREFETCH_AHEAD = 16

_ENABLED = os.environ.get("LIGHTSTAGE_HASHGRID_KERNEL", "numba") != "torch"
_POOL: ThreadPoolExecutor | None = None
_POOL_SIZE = 0
_POOL_LOCK = threading.Lock()


def available() -> bool:
    """True when the fused CPU kernels can run (numba importable and not switched off)."""
    return numba is not None and _ENABLED


def set_enabled(enabled: bool) -> bool:
    """Switch the fused CPU kernels on or off (benches and tests compare both paths); returns the old state."""
    global _ENABLED
    old, _ENABLED = _ENABLED, bool(enabled)
    return old


if numba is not None:

    @intrinsic
    def _prefetch_row(typingctx, table, row, write):
        """Hint the cache to fetch table[row, 0] (LLVM's prefetch; `write` a literal 0 or 1, locality 3)."""
        if not isinstance(write, types.IntegerLiteral):
            return None
        sig = types.void(table, row, write)

        def codegen(context, builder, signature, args):
            aryty = signature.args[0]
            ary = context.make_array(aryty)(context, builder, args[0])
            zero = context.get_constant(types.intp, 0)
            ptr = cgutils.get_item_pointer(context, builder, aryty, ary, [args[1], zero])
            i8p = builder.bitcast(ptr, ir.IntType(8).as_pointer())
            i32 = ir.IntType(32)
            fnty = ir.FunctionType(ir.VoidType(), [i8p.type, i32, i32, i32])
            fn = cgutils.get_or_insert_function(builder.module, fnty, "llvm.prefetch")
            rw = ir.Constant(i32, signature.args[2].literal_value)
            builder.call(fn, [i8p, rw, ir.Constant(i32, 3), ir.Constant(i32, 1)])
            return context.get_dummy_value()

        return sig, codegen

    @numba.njit(nogil=True, cache=True)
    def _prefetch_corners(u, m, rf, ri, dn, stride, mask, px_, py_, pz_, tab, write):
        """Prefetch the 8 corner rows of point m (for reading, or for writing when `write` is 1). The cell and
        hash are computed again when m's turn comes: a few integer ops, cheaper than keeping a ring of them."""
        cx, cy, cz, _, _, _ = _corner_cells(u, m, rf, ri)
        for k in range(8):
            _prefetch_row(tab, _corner_index(cx, cy, cz, k, dn, stride, mask, px_, py_, pz_), write)

    @numba.njit(nogil=True, cache=True)
    def _corner_cells(u, n, res_f, res_i):
        """Cell (cx, cy, cz) and fractions (fx, fy, fz) of point n at one level's resolution, in float32."""
        px = u[n, 0] * res_f
        py = u[n, 1] * res_f
        pz = u[n, 2] * res_f
        cx = min(np.int64(px), res_i - 1)
        cy = min(np.int64(py), res_i - 1)
        cz = min(np.int64(pz), res_i - 1)
        return cx, cy, cz, px - np.float32(cx), py - np.float32(cy), pz - np.float32(cz)

    @numba.njit(nogil=True, cache=True)
    def _corner_index(cx, cy, cz, k, dense, stride, mask, px_, py_, pz_):
        """Table row of corner k (bit 0: +x, bit 1: +y, bit 2: +z) of cell (cx, cy, cz)."""
        x = cx + (k & 1)
        y = cy + ((k >> 1) & 1)
        z = cz + ((k >> 2) & 1)
        if dense:
            return x + stride * (y + stride * z)
        return ((x * px_) ^ (y * py_) ^ (z * pz_)) & mask

    @numba.njit(nogil=True, cache=True)
    def _corner_weight(k, fx, fy, fz):
        """Trilinear weight of corner k, multiplied as the PyTorch path does: (wx * wy) * wz."""
        one = np.float32(1.0)
        wx = fx if k & 1 else one - fx
        wy = fy if (k >> 1) & 1 else one - fy
        wz = fz if (k >> 2) & 1 else one - fz
        return (wx * wy) * wz

    @numba.njit(nogil=True, cache=True)
    def _forward_levels(u, table, res_f, res_i, dense, primes, levels, out):
        """out[l, n, f] = sum_k w_k * table[l, idx_k, f] for the given levels (level-major: each level's rows
        are written contiguously)."""
        n_pts, size, nf = u.shape[0], table.shape[1], table.shape[2]
        mask = size - 1
        px_, py_, pz_ = primes[0], primes[1], primes[2]
        for level in levels:
            rf, ri, dn = res_f[level], res_i[level], dense[level]
            stride = ri + 1
            tab, dst = table[level], out[level]
            for n in range(n_pts):
                if n + PREFETCH_AHEAD < n_pts:
                    m = n + PREFETCH_AHEAD
                    _prefetch_corners(u, m, rf, ri, dn, stride, mask, px_, py_, pz_, tab, 0)
                cx, cy, cz, fx, fy, fz = _corner_cells(u, n, rf, ri)
                if nf == 2:  # the common layout: two accumulators in registers
                    a0 = np.float32(0.0)
                    a1 = np.float32(0.0)
                    for k in range(8):
                        idx = _corner_index(cx, cy, cz, k, dn, stride, mask, px_, py_, pz_)
                        w = _corner_weight(k, fx, fy, fz)
                        a0 += w * tab[idx, 0]
                        a1 += w * tab[idx, 1]
                    dst[n, 0] = a0
                    dst[n, 1] = a1
                    continue
                for f in range(nf):
                    dst[n, f] = 0.0
                for k in range(8):
                    idx = _corner_index(cx, cy, cz, k, dn, stride, mask, px_, py_, pz_)
                    w = _corner_weight(k, fx, fy, fz)
                    for f in range(nf):
                        dst[n, f] += w * tab[idx, f]

    @numba.njit(nogil=True, cache=True)
    def _backward_levels(u, grad_out, res_f, res_i, dense, primes, levels, grad_table):
        """grad_table[l] = sum over points of w_k * grad_out[l, n, f] scattered to rows idx_k, for the given
        levels (each level's slice is zeroed here first, by the thread that owns it)."""
        n_pts, size, nf = u.shape[0], grad_table.shape[1], grad_table.shape[2]
        mask = size - 1
        px_, py_, pz_ = primes[0], primes[1], primes[2]
        for level in levels:
            rf, ri, dn = res_f[level], res_i[level], dense[level]
            stride = ri + 1
            gt, src = grad_table[level], grad_out[level]
            gt[:] = 0.0
            for n in range(n_pts):
                if n + PREFETCH_AHEAD < n_pts:
                    m = n + PREFETCH_AHEAD
                    _prefetch_corners(u, m, rf, ri, dn, stride, mask, px_, py_, pz_, gt, 1)
                cx, cy, cz, fx, fy, fz = _corner_cells(u, n, rf, ri)
                if nf == 2:
                    g0, g1 = src[n, 0], src[n, 1]
                    for k in range(8):
                        idx = _corner_index(cx, cy, cz, k, dn, stride, mask, px_, py_, pz_)
                        w = _corner_weight(k, fx, fy, fz)
                        gt[idx, 0] += w * g0
                        gt[idx, 1] += w * g1
                    continue
                for k in range(8):
                    idx = _corner_index(cx, cy, cz, k, dn, stride, mask, px_, py_, pz_)
                    w = _corner_weight(k, fx, fy, fz)
                    for f in range(nf):
                        gt[idx, f] += w * src[n, f]

    @numba.njit(nogil=True, cache=True)
    def _swap_leading(src, dst):
        """dst[j, i, f] = src[i, j, f]: between the kernels' level-major (L, N, F) layout and the (N, L, F) rows
        the MLP reads (4-5x faster than PyTorch's strided copy of the permuted view on the VMs measured)."""
        a, b, nf = src.shape
        for j in range(b):
            for i in range(a):
                for f in range(nf):
                    dst[j, i, f] = src[i, j, f]


def _pool(workers: int) -> ThreadPoolExecutor:
    """The shared pool, grown (never shrunk) to `workers` threads."""
    global _POOL, _POOL_SIZE
    with _POOL_LOCK:
        if _POOL is None or _POOL_SIZE < workers:
            old, _POOL, _POOL_SIZE = (
                _POOL,
                ThreadPoolExecutor(workers, thread_name_prefix="hashgrid"),
                workers,
            )
            if old is not None:
                old.shutdown(wait=False)
        return _POOL


def _forget_pool() -> None:
    """In a forked child: the parent's pool threads do not exist there, so start a new pool when needed."""
    global _POOL, _POOL_SIZE, _POOL_LOCK
    _POOL, _POOL_SIZE, _POOL_LOCK = None, 0, threading.Lock()


os.register_at_fork(after_in_child=_forget_pool)


def _run_by_level(kernel, levels: int, *args) -> None:
    """Call `kernel(*args[:-1], level_subset, args[-1])` on interleaved level subsets, one per torch thread."""
    workers = max(1, min(torch.get_num_threads(), levels))
    parts = [np.arange(k, levels, workers, dtype=np.int64) for k in range(workers)]
    if workers == 1:
        kernel(*args[:-1], parts[0], args[-1])
        return
    futures = [_pool(workers).submit(kernel, *args[:-1], p, args[-1]) for p in parts]
    for fut in futures:
        fut.result()


class FusedLookup(torch.autograd.Function):
    """(N, 3) unit-cube positions u in [0, 1] and (L, T, F) float32 tables -> (N, L * F) features on CPU, given
    per level its resolution (float32 and int64) and whether it is dense, and the hash primes mod T; with
    the table gradient from the same kernel arithmetic. Positions get no gradient (they are not optimised)."""

    @staticmethod
    def forward(ctx, tables, u, res_f, res_i, dense, primes):
        if not bool(
            torch.isfinite(u).all()
        ):  # a NaN cell index would read outside the table (no bounds checks)
            raise ValueError("hash grid: non-finite sample positions")
        un = u.detach().contiguous().numpy()
        tab = tables.detach().contiguous().numpy()
        levels, _, nf = tab.shape
        by_level = np.empty((levels, un.shape[0], nf), dtype=np.float32)
        _run_by_level(_forward_levels, levels, un, tab, res_f, res_i, dense, primes, by_level)
        out = torch.empty(un.shape[0], levels, nf)
        _swap_leading(by_level, out.numpy())
        ctx.save_for_backward(u)
        ctx.meta = (res_f, res_i, dense, primes, tables.shape)
        return out.view(un.shape[0], levels * nf)

    @staticmethod
    def backward(ctx, grad):
        (u,) = ctx.saved_tensors
        res_f, res_i, dense, primes, shape = ctx.meta
        g = torch.empty(shape)  # each level is zeroed by the kernel thread that fills it
        n, levels, nf = grad.shape[0], shape[0], shape[2]
        go = np.empty((levels, n, nf), dtype=np.float32)
        _swap_leading(grad.detach().float().contiguous().view(n, levels, nf).numpy(), go)
        _run_by_level(
            _backward_levels,
            levels,
            u.detach().contiguous().numpy(),
            go,
            res_f,
            res_i,
            dense,
            primes,
            g.numpy(),
        )
        return g, None, None, None, None, None
