"""The hash encoding's CPU kernels: lookup and its table gradient fused per level in numba, so no (8, levels, N)
index or weight array is materialised and the gradient is scattered straight into a float32 table.

The arithmetic is `HashGridEncoding`'s (float32 positions, the int32-exact spatial hash, the same corner order);
the PyTorch path stays for CUDA and as the reference. Work is split by level over a small thread pool of
GIL-free calls: each level is one thread's alone, so the scatter needs no atomics, and results do not depend
on the thread count. Numba's own parallel layers are avoided on purpose (the `omp` one is not fork-safe with
GNU OpenMP, `workqueue` not thread-safe). The features come out as (L * F, N) rows, returned as their
transpose: the MLP's products read that column-major (N, L * F) as is, and its gradient comes back in the same
layout, so no transposing copy runs either way.
"""

from __future__ import annotations

import os
import threading
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import torch

from lightstage.kernel_switch import KernelSwitch

try:
    import numba
    from llvmlite import ir
    from numba.core import cgutils, types
    from numba.extending import intrinsic
except ImportError:  # pragma: no cover - numba is a dependency; the PyTorch path still works without it
    numba = None

# Points ahead whose corner rows are prefetched: the rows of the hashed levels are random reads into 4 MB
# tables, so without it a point waits on its own misses (forward 12.4 -> 8.1 ms for `fast`'s 44 k samples on
# the AMD EPYC VM, cold caches; 8-32 all within noise of 16; docs/benchmarks.md). Each point's hashed rows are
# computed once, when it enters a ring of this many slots (indexed n & (PREFETCH_AHEAD - 1): a power of two)
PREFETCH_AHEAD = 16
assert PREFETCH_AHEAD & (PREFETCH_AHEAD - 1) == 0

_SWITCH = KernelSwitch("LIGHTSTAGE_HASHGRID_KERNEL", "torch", numba is not None)
available = _SWITCH.available  # numba importable and not switched off
set_enabled = _SWITCH.set_enabled  # benches and tests compare both paths
_POOL: ThreadPoolExecutor | None = None
_POOL_SIZE = 0
_POOL_LOCK = threading.Lock()


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

    @numba.njit(nogil=True, cache=True, inline="always")
    def _corner_cells(u, n, res_f, res_i):
        """Cell (cx, cy, cz) and fractions (fx, fy, fz) of point n at one level's resolution, in float32."""
        px = u[n, 0] * res_f
        py = u[n, 1] * res_f
        pz = u[n, 2] * res_f
        cx = min(np.int64(px), res_i - 1)
        cy = min(np.int64(py), res_i - 1)
        cz = min(np.int64(pz), res_i - 1)
        return cx, cy, cz, px - np.float32(cx), py - np.float32(cy), pz - np.float32(cz)

    @numba.njit(nogil=True, cache=True, inline="always")
    def _hashed_corners(cx, cy, cz, mask, px_, py_, pz_, idx):
        """idx[k] = table row of corner k (bit 0: +x, bit 1: +y, bit 2: +z) of cell (cx, cy, cz) through the
        spatial hash; (c + 1) * p = c * p + p, so each axis costs one product and the 8 rows 12 xors."""
        x0, y0, z0 = cx * px_, cy * py_, cz * pz_
        x1, y1, z1 = x0 + px_, y0 + py_, z0 + pz_
        a, b, c, d = x0 ^ y0, x1 ^ y0, x0 ^ y1, x1 ^ y1
        idx[0], idx[1], idx[2], idx[3] = (a ^ z0) & mask, (b ^ z0) & mask, (c ^ z0) & mask, (d ^ z0) & mask
        idx[4], idx[5], idx[6], idx[7] = (a ^ z1) & mask, (b ^ z1) & mask, (c ^ z1) & mask, (d ^ z1) & mask

    @numba.njit(nogil=True, cache=True, inline="always")
    def _dense_offsets(stride):
        """Row offsets of the 8 corners from corner 0, dense level (row = x + stride * (y + stride * z))."""
        s2 = stride * stride
        return np.array([0, 1, stride, stride + 1, s2, s2 + 1, s2 + stride, s2 + stride + 1], dtype=np.int64)

    @numba.njit(nogil=True, cache=True, inline="always")
    def _corner_weights(fx, fy, fz, w):
        """w[k] = trilinear weight of corner k, multiplied as the PyTorch path does: (wx * wy) * wz."""
        one = np.float32(1.0)
        gx, gy, gz = one - fx, one - fy, one - fz
        w00, w10, w01, w11 = gx * gy, fx * gy, gx * fy, fx * fy
        w[0], w[1], w[2], w[3] = w00 * gz, w10 * gz, w01 * gz, w11 * gz
        w[4], w[5], w[6], w[7] = w00 * fz, w10 * fz, w01 * fz, w11 * fz

    @numba.njit(nogil=True, cache=True, inline="always")
    def _dense_point(u, n, rf, ri, w):
        """Dense levels: the row of point n's corner 0 (x + (r + 1) * (y + (r + 1) * z)); its weights into w."""
        cx, cy, cz, fx, fy, fz = _corner_cells(u, n, rf, ri)
        _corner_weights(fx, fy, fz, w)
        return cx + (ri + 1) * (cy + (ri + 1) * cz)

    @numba.njit(nogil=True, cache=True, inline="always")
    def _ring_in(u, m, rf, ri, mask, px_, py_, pz_, ring, tab, write):
        """Hashed levels: point m's corner rows into ring slot m % PREFETCH_AHEAD, and ask the cache for them
        (`write` 1: for writing). Point n's slot is refilled with point n + PREFETCH_AHEAD once n is done."""
        slot = m & (PREFETCH_AHEAD - 1)
        cx, cy, cz, _, _, _ = _corner_cells(u, m, rf, ri)
        _hashed_corners(cx, cy, cz, mask, px_, py_, pz_, ring[slot])
        for k in range(8):
            _prefetch_row(tab, ring[slot, k], write)

    @numba.njit(nogil=True, cache=True, inline="always")
    def _ring_fill(u, n_pts, rf, ri, mask, px_, py_, pz_, ring, tab, write):
        """Hashed levels: the ring's first slots with points 0 .. PREFETCH_AHEAD - 1 (before a level's loop)."""
        for m in range(min(PREFETCH_AHEAD, n_pts)):
            _ring_in(u, m, rf, ri, mask, px_, py_, pz_, ring, tab, write)

    @numba.njit(nogil=True, cache=True, inline="always")
    def _hashed_point(u, n, rf, ri, w):
        """Hashed levels: the ring slot that holds point n's corner rows; its weights into w."""
        _, _, _, fx, fy, fz = _corner_cells(u, n, rf, ri)
        _corner_weights(fx, fy, fz, w)
        return n & (PREFETCH_AHEAD - 1)

    @numba.njit(nogil=True, cache=True)
    def _level_rows(u, rf, ri, dense, mask, primes, rows, w):
        """Generic path (any features per row): every point's 8 corner rows and weights, (N, 8) each."""
        offsets = _dense_offsets(ri + 1)
        for n in range(u.shape[0]):
            if dense:
                r0 = _dense_point(u, n, rf, ri, w[n])
                for k in range(8):
                    rows[n, k] = r0 + offsets[k]
            else:
                cx, cy, cz, fx, fy, fz = _corner_cells(u, n, rf, ri)
                _corner_weights(fx, fy, fz, w[n])
                _hashed_corners(cx, cy, cz, mask, primes[0], primes[1], primes[2], rows[n])

    @numba.njit(nogil=True, cache=True)
    def _forward_levels(u, table, res_f, res_i, dense, offsets, primes, levels, out):
        """out[l, f, n] = sum_k w_k * table[l, idx_k, f] for the given levels (each level's features are
        contiguous rows over the points: the MLP's input, column-major). Two-feature rows (the common layout)
        run a loop per level kind: dense levels from the cell's first row plus fixed offsets, hashed levels
        from a ring of the rows of the next PREFETCH_AHEAD points, computed once each and prefetched; other
        widths a generic loop."""
        n_pts, nf = u.shape[0], table.shape[1]
        px_, py_, pz_ = primes[0], primes[1], primes[2]
        w = np.empty(8, dtype=np.float32)
        ring = np.empty((PREFETCH_AHEAD, 8), dtype=np.int64)
        for level in levels:
            rf, ri = res_f[level], res_i[level]
            tab, dst = table[offsets[level] : offsets[level + 1]], out[level]
            mask = tab.shape[0] - 1  # hashed levels: T rows, a power of two
            if nf != 2:
                rows, ws = np.empty((n_pts, 8), np.int64), np.empty((n_pts, 8), np.float32)
                _level_rows(u, rf, ri, dense[level], mask, primes, rows, ws)
                for n in range(n_pts):
                    for f in range(nf):
                        dst[f, n] = 0.0
                    for k in range(8):
                        for f in range(nf):
                            dst[f, n] += ws[n, k] * tab[rows[n, k], f]
            elif dense[level]:
                off = _dense_offsets(ri + 1)
                for n in range(n_pts):
                    base = _dense_point(u, n, rf, ri, w)
                    a0 = np.float32(0.0)
                    a1 = np.float32(0.0)
                    for k in range(8):
                        r = base + off[k]
                        a0 += w[k] * tab[r, 0]
                        a1 += w[k] * tab[r, 1]
                    dst[0, n] = a0
                    dst[1, n] = a1
            else:
                _ring_fill(u, n_pts, rf, ri, mask, px_, py_, pz_, ring, tab, 0)
                for n in range(n_pts):
                    slot = _hashed_point(u, n, rf, ri, w)
                    a0 = np.float32(0.0)
                    a1 = np.float32(0.0)
                    for k in range(8):
                        r = ring[slot, k]
                        a0 += w[k] * tab[r, 0]
                        a1 += w[k] * tab[r, 1]
                    dst[0, n] = a0
                    dst[1, n] = a1
                    if n + PREFETCH_AHEAD < n_pts:  # n's slot, now free
                        _ring_in(u, n + PREFETCH_AHEAD, rf, ri, mask, px_, py_, pz_, ring, tab, 0)

    @numba.njit(nogil=True, cache=True)
    def _backward_levels(u, grad_out, res_f, res_i, dense, offsets, primes, levels, grad_table):
        """grad_table[l] = sum over points of w_k * grad_out[l, f, n] scattered to rows idx_k, for the given
        levels (each level's slice is zeroed here first, by the thread that owns it); loops as the forward's,
        the prefetch asking for the rows to write."""
        n_pts, nf = u.shape[0], grad_table.shape[1]
        px_, py_, pz_ = primes[0], primes[1], primes[2]
        w = np.empty(8, dtype=np.float32)
        ring = np.empty((PREFETCH_AHEAD, 8), dtype=np.int64)
        for level in levels:
            rf, ri = res_f[level], res_i[level]
            gt, src = grad_table[offsets[level] : offsets[level + 1]], grad_out[level]
            mask = gt.shape[0] - 1
            gt[:] = 0.0
            if nf != 2:
                rows, ws = np.empty((n_pts, 8), np.int64), np.empty((n_pts, 8), np.float32)
                _level_rows(u, rf, ri, dense[level], mask, primes, rows, ws)
                for n in range(n_pts):
                    for k in range(8):
                        for f in range(nf):
                            gt[rows[n, k], f] += ws[n, k] * src[f, n]
            elif dense[level]:
                off = _dense_offsets(ri + 1)
                for n in range(n_pts):
                    base = _dense_point(u, n, rf, ri, w)
                    g0, g1 = src[0, n], src[1, n]
                    for k in range(8):
                        r = base + off[k]
                        gt[r, 0] += w[k] * g0
                        gt[r, 1] += w[k] * g1
            else:
                _ring_fill(u, n_pts, rf, ri, mask, px_, py_, pz_, ring, gt, 1)
                for n in range(n_pts):
                    slot = _hashed_point(u, n, rf, ri, w)
                    g0, g1 = src[0, n], src[1, n]
                    for k in range(8):
                        r = ring[slot, k]
                        gt[r, 0] += w[k] * g0
                        gt[r, 1] += w[k] * g1
                    if n + PREFETCH_AHEAD < n_pts:
                        _ring_in(u, n + PREFETCH_AHEAD, rf, ri, mask, px_, py_, pz_, ring, gt, 1)


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
    """(N, 3) unit-cube positions u in [0, 1] and the packed (rows, F) float32 tables -> (N, L * F) features
    on CPU, given per level its resolution (float32 and int64), whether it is dense, and its first row (L + 1
    offsets: level l holds rows [o_l, o_l+1)), and the hash primes mod T; with the table gradient from the
    same kernel arithmetic. Positions get no gradient (they are not optimised)."""

    @staticmethod
    def forward(ctx, tables, u, res_f, res_i, dense, offsets, primes):
        if not bool(
            torch.isfinite(u).all()
        ):  # a NaN cell index would read outside the table (no bounds checks)
            raise ValueError("hash grid: non-finite sample positions")
        un = u.detach().contiguous().numpy()
        tab = tables.detach().contiguous().numpy()
        levels, nf = len(res_f), tab.shape[1]
        out = torch.empty(levels * nf, un.shape[0])  # (L, F, N): each level's features as contiguous rows
        kernel_args = (res_f, res_i, dense, offsets, primes)
        _run_by_level(_forward_levels, levels, un, tab, *kernel_args, out.view(levels, nf, -1).numpy())
        ctx.save_for_backward(u)
        ctx.meta = (kernel_args, tables.shape)
        return out.t()  # (N, L * F), column-major: BLAS reads it as is (no transposing copy)

    @staticmethod
    def backward(ctx, grad):
        (u,) = ctx.saved_tensors
        kernel_args, shape = ctx.meta
        g = torch.empty(shape)  # each level is zeroed by the kernel thread that fills it
        levels, nf = len(kernel_args[0]), shape[1]
        # (L * F, N) rows, as the forward returned them: the fused MLPs' gradient comes in that layout already
        go = grad.detach().float().t().contiguous().view(levels, nf, -1)
        un = u.detach().contiguous().numpy()
        _run_by_level(_backward_levels, levels, un, go.numpy(), *kernel_args, g.numpy())
        return g, None, None, None, None, None, None
