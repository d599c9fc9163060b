"""The hash-grid field's two MLPs (density, then transfer head) as one autograd function that runs over chunks of
samples, so on CPU every (chunk, hidden) activation stays in cache instead of streaming (N, hidden) arrays
through memory once per ReLU, bias and gradient op.

Forward per chunk: g = geo(enc) (ReLU between layers), pre = g[:, 1:] @ Wf^T + bf + ray_term[rows] (computed
as g @ [0 | Wf]^T), then the head's remaining layers (ReLU before each). Each chunk's activations are kept for
the backward, which walks the chunks again and accumulates the weight gradients (recomputing them instead was
10-15 % slower per `fast` step on the AMD EPYC VM measured; docs/benchmarks.md). The arithmetic is
`nn.Linear`'s and `nn.ReLU`'s; `HashGridField` uses the module path on CUDA and as the reference.
"""

from __future__ import annotations

import torch

CHUNK = 16384  # samples per chunk: (16384, 64) float32 is 4 MB, within the L3 of the CPUs measured


def _pairs(flat, n_geo: int) -> tuple[list, list]:
    """(geo layers, head layers) as (weight, bias) pairs from the flat parameter list, geo's `n_geo` first."""
    layers = list(zip(flat[0::2], flat[1::2], strict=True))
    return layers[:n_geo], layers[n_geo:]


def _relu_grad(grad: torch.Tensor, activated: torch.Tensor) -> torch.Tensor:
    """d relu: the gradient where the ReLU's output is positive, 0 elsewhere."""
    return torch.ops.aten.threshold_backward(grad, activated, 0.0)


def _forward_chunk(enc, ray_rows, geo, head, wf_pad):
    """Activations of one chunk: [geo layer inputs..., g, head layer inputs...], and the head's raw output.
    `wf_pad` is the head's first weight with a zero column for g's density column, so its product reads the
    contiguous g (a product over the strided g[:, 1:] and 15 columns ran at a third of the others' speed)."""
    acts = [enc]
    x = enc
    for i, (w, b) in enumerate(geo):
        x = torch.addmm(b, x, w.t())
        if i < len(geo) - 1:
            x = x.relu_()
        acts.append(x)
    g = x
    x = torch.addmm(head[0][1], g, wf_pad.t()).add_(ray_rows)
    for w, b in head[1:]:
        x = x.relu_()
        acts.append(x)
        x = torch.addmm(b, x, w.t())
    return acts, g, x


def _pad_first(wf: torch.Tensor) -> torch.Tensor:
    """The head's first weight (H, G - 1) with a zero first column: (H, G), applied to the whole g."""
    return torch.cat([wf.new_zeros(wf.shape[0], 1), wf], 1)


class _FieldMLP(torch.autograd.Function):
    @staticmethod
    def forward(ctx, enc, ray_term, rows, n_geo, chunk, *params):
        geo, head = _pairs(params, n_geo)
        n = len(enc)
        g_out = enc.new_empty(n, geo[-1][0].shape[0])
        h_out = enc.new_empty(n, head[-1][0].shape[0])
        wf_pad = _pad_first(head[0][0])
        ctx.chunks = []  # per chunk (layer inputs, g): the backward's activations
        for i in range(0, n, chunk):
            ray_rows = ray_term.index_select(0, rows[i : i + chunk])
            acts, g, h = _forward_chunk(enc[i : i + chunk], ray_rows, geo, head, wf_pad)
            ctx.chunks.append((acts, g))
            g_out[i : i + chunk] = g
            h_out[i : i + chunk] = h
        ctx.save_for_backward(enc, ray_term, rows, *params)
        ctx.n_geo, ctx.chunk = n_geo, chunk
        return g_out, h_out

    @staticmethod
    def backward(ctx, grad_g, grad_h):
        enc, ray_term, rows, *params = ctx.saved_tensors
        n_geo, chunk = ctx.n_geo, ctx.chunk
        geo, head = _pairs(params, n_geo)
        grads = [torch.zeros_like(p) for p in params]
        g_geo, g_head = _pairs(grads, n_geo)
        d_enc = torch.empty_like(enc) if ctx.needs_input_grad[0] else None
        d_ray = torch.zeros_like(ray_term) if ctx.needs_input_grad[1] else None
        wf_pad = _pad_first(head[0][0])
        dwf_pad = torch.zeros_like(wf_pad)
        if grad_g is None:
            grad_g = enc.new_zeros(len(enc), geo[-1][0].shape[0])
        if grad_h is None:
            grad_h = enc.new_zeros(len(enc), head[-1][0].shape[0])
        for i in range(0, len(enc), chunk):
            r = rows[i : i + chunk]
            acts, g = ctx.chunks[i // chunk]
            head_in = acts[n_geo + 1 :]
            d = grad_h[i : i + chunk]
            for k in range(len(head) - 1, 0, -1):  # head layers after the first; head_in[k - 1] feeds layer k
                (w, _), (dw, db) = head[k], g_head[k]
                dw.addmm_(d.t(), head_in[k - 1])
                db += d.sum(0)
                d = _relu_grad(d @ w, head_in[k - 1])
            dwf_pad.addmm_(d.t(), g)
            g_head[0][1].add_(d.sum(0))
            if d_ray is not None:
                d_ray.index_add_(0, r, d)
            d = torch.addmm(grad_g[i : i + chunk], d, wf_pad)  # column 0 of wf_pad is 0
            for k in range(n_geo - 1, -1, -1):  # acts[k] is geo layer k's input
                (w, _), (dw, db) = geo[k], g_geo[k]
                dw.addmm_(d.t(), acts[k])
                db += d.sum(0)
                if k > 0:
                    d = _relu_grad(d @ w, acts[k])
                elif d_enc is not None:
                    torch.mm(d, w, out=d_enc[i : i + chunk])
        g_head[0][0].copy_(dwf_pad[:, 1:])
        return (d_enc, d_ray, None, None, None, *grads)


def field_mlp(
    enc: torch.Tensor,
    ray_term: torch.Tensor,
    rows: torch.Tensor,
    geo: list[tuple[torch.Tensor, torch.Tensor]],
    head: list[tuple[torch.Tensor, torch.Tensor]],
    chunk: int | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """(geo output (N, G), head output before its activation (N, 3)) for encodings (N, E), the head's per-ray
    first-layer term (R, H) and each sample's ray `rows` (N,): the density MLP `geo` (ReLU between its layers),
    then the head, whose first layer takes the geo output's columns 1: plus ray_term[rows]; layers as
    (weight (out, in), bias (out,)) pairs, `nn.Linear`'s layout."""
    params = [t for layer in (*geo, *head) for t in layer]
    return _FieldMLP.apply(enc, ray_term, rows, len(geo), chunk or CHUNK, *params)
