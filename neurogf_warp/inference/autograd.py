"""Differentiable queries in torch: gradients with respect to the query points, from Warp kernels.

``distance``, ``ssad`` (from a point), ``msad`` (from points) and ``sdf`` take torch tensors with
``requires_grad``; their results then carry a ``grad_fn`` whose backward launches the per-thread gradient
kernels of ``kernels/inference/mlp.py`` (the in-kernel API's ``distance_and_gradient`` and
``signed_distance_and_gradient``: float32 weights, float64 sums). Forward values are the ordinary query's,
bit for bit. Where the answer is the straight line (the network's value fell below |p - q|), the gradient is the
straight line's; at p = q, across parts of the mesh (+inf) and for NaN rows it is 0.

The query module passes its plain functions in (this module sits below it). Gradients with respect to the
network's weights are not offered: the queries run on folded, frozen weights
(BatchNorm folded in, fp16 packed on tensor cores); to train through distances use ``model.net`` in torch.
"""
from __future__ import annotations

import numpy as np
import torch
import warp as wp

from neurogf_warp.common.arrays import resolve_device
from neurogf_warp.common.checks import InputError
from neurogf_warp.inference.state import query_state
from neurogf_warp.kernels.inference import mlp

__all__ = ["wants_grad", "distance", "ssad", "msad", "sdf"]


def wants_grad(*xs) -> bool:
    """True when a query's result must carry a gradient: some input is a torch tensor that requires one."""
    return torch.is_grad_enabled() and any(isinstance(x, torch.Tensor) and x.requires_grad for x in xs)


@wp.kernel
def _pair_grad(net: mlp.NeuroGFWeights, fr: mlp.Frame, P: wp.array(dtype=wp.vec3), Q: wp.array(dtype=wp.vec3),
               d: wp.array(dtype=float), gout: wp.array(dtype=float), raw: int,
               gP: wp.array(dtype=wp.vec3), gQ: wp.array(dtype=wp.vec3)):
    i = wp.tid()
    di = d[i]
    gP[i] = wp.vec3(0.0)
    gQ[i] = wp.vec3(0.0)
    if not wp.isfinite(di) or di == 0.0:
        return
    p = P[i]
    q = Q[i]
    chain = gout[i] * fr.dscale * fr.xscale
    pn = mlp.to_net(fr, p)
    qn = mlp.to_net(fr, q)
    dp, gp = mlp.distance_and_gradient(net, pn, qn)
    dq, gq = mlp.distance_and_gradient(net, qn, pn)  # the head is symmetric: dq = dp
    e = wp.length(p - q)
    if raw == 0 and e > 0.0 and di <= e * 1.000001:
        # the answer was raised to the straight line: its gradient
        u = (p - q) / e
        gP[i] = gout[i] * u
        gQ[i] = -gout[i] * u
        return
    gP[i] = chain * gp
    gQ[i] = chain * gq


@wp.kernel
def _sdf_grad(net: mlp.NeuroGFWeights, fr: mlp.Frame, X: wp.array(dtype=wp.vec3), s: wp.array(dtype=float),
              gout: wp.array(dtype=float), gX: wp.array(dtype=wp.vec3)):
    i = wp.tid()
    gX[i] = wp.vec3(0.0)
    if not wp.isfinite(s[i]):
        return
    v, g = mlp.signed_distance_and_gradient(net, mlp.to_net(fr, X[i]))
    gX[i] = (gout[i] * fr.dscale * fr.xscale) * g


def _vec3(t: torch.Tensor, dev) -> wp.array:
    return wp.from_torch(t.detach().to(torch.float32).contiguous().reshape(-1, 3), dtype=wp.vec3)


def _pair_gradients(model, P: torch.Tensor, Q: torch.Tensor, d: torch.Tensor, gout: torch.Tensor, raw: bool):
    """(dL/dP, dL/dQ), (N, 3) each, for distances ``d`` = d(P, Q) (mesh units) and upstream gradients ``gout``."""
    dev = resolve_device(None, like=P)
    st = query_state(model, dev)
    n = P.shape[0]
    gP = torch.empty((n, 3), dtype=torch.float32, device=P.device)
    gQ = torch.empty((n, 3), dtype=torch.float32, device=P.device)
    if n:
        wp.launch(_pair_grad, n, inputs=[st.weights, st.user_frame, _vec3(P, dev), _vec3(Q, dev),
                                         wp.from_torch(d.detach().float().contiguous()),
                                         wp.from_torch(gout.detach().float().contiguous()), int(raw)],
                  outputs=[wp.from_torch(gP, dtype=wp.vec3), wp.from_torch(gQ, dtype=wp.vec3)], device=dev)
    return gP, gQ


class _Distance(torch.autograd.Function):
    @staticmethod
    def forward(ctx, p, q, model, kw, plain):
        d = plain(model, p.detach(), q.detach(), **kw)
        ctx.model, ctx.raw = model, kw["raw"]
        ctx.save_for_backward(p, q, d)
        return d

    @staticmethod
    def backward(ctx, g):
        p, q, d = ctx.saved_tensors
        P, Q = p.reshape(-1, 3), q.reshape(-1, 3)
        gP, gQ = _pair_gradients(ctx.model, P, Q, d.reshape(-1), g.reshape(-1), ctx.raw)
        return gP.reshape(p.shape).to(p.dtype), gQ.reshape(q.shape).to(q.dtype), None, None, None


def _vertices_like(model, x: torch.Tensor) -> torch.Tensor:
    """The mesh's vertices in the file's numbering, float32 on ``x``'s device (NaN rows for unused vertices)."""
    m = model.mesh
    v = np.full((m.n_input, 3), np.nan)
    used = m.input_to_internal >= 0
    v[used] = m.internal_vertices[m.input_to_internal[used]]
    return torch.as_tensor(v, dtype=torch.float32, device=x.device)


class _Sources(torch.autograd.Function):
    """ssad from one point / msad from points: (S, 3) sources -> (n_input,) distances to the nearest source."""

    @staticmethod
    def forward(ctx, src, model, kw, one, plain, matrix):
        d = plain(model, src.detach(), output="torch", **kw)
        ctx.model, ctx.kw, ctx.one, ctx.matrix = model, kw, one, matrix
        ctx.save_for_backward(src, d)
        return d

    @staticmethod
    def backward(ctx, g):
        src, d = ctx.saved_tensors
        S = src.reshape(-1, 3)
        V = _vertices_like(ctx.model, S)
        if ctx.one or S.shape[0] == 1:
            nearest = torch.zeros(V.shape[0], dtype=torch.int64, device=S.device)
        else:  # each vertex's gradient goes to its nearest source
            M = ctx.matrix(ctx.model, S.detach(), output="torch", **ctx.kw)
            nearest = torch.argmin(torch.nan_to_num(M, nan=float("inf")), 0)
        gP, _ = _pair_gradients(ctx.model, S[nearest].detach(), V, d.reshape(-1), g.reshape(-1),
                                ctx.kw.get("raw", False))
        gS = torch.zeros_like(S, dtype=torch.float32).index_add_(0, nearest, torch.nan_to_num(gP))
        return gS.reshape(src.shape).to(src.dtype), None, None, None, None, None


class _Sdf(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x, model, kw, plain):
        s = plain(model, x.detach(), **kw)
        ctx.model = model
        ctx.save_for_backward(x, s)
        return s

    @staticmethod
    def backward(ctx, g):
        x, s = ctx.saved_tensors
        X = x.reshape(-1, 3)
        dev = resolve_device(None, like=X)
        st = query_state(ctx.model, dev)
        gX = torch.empty((X.shape[0], 3), dtype=torch.float32, device=X.device)
        if X.shape[0]:
            wp.launch(_sdf_grad, X.shape[0], inputs=[st.weights, st.user_frame, _vec3(X, dev),
                                                     wp.from_torch(s.detach().reshape(-1).float().contiguous()),
                                                     wp.from_torch(g.detach().reshape(-1).float().contiguous())],
                      outputs=[wp.from_torch(gX, dtype=wp.vec3)], device=dev)
        return gX.reshape(x.shape).to(x.dtype), None, None, None


def _float_tensor(x, name: str) -> torch.Tensor:
    if not torch.is_floating_point(x):
        raise TypeError(f"{name} requires a gradient, so it must be a floating-point tensor, got {x.dtype}")
    return x


def _no_landmarks(model):
    """The gradient kernels here run the plain distance head: a landmark network's is refused, naming the in-kernel
    function that has its gradient."""
    k = getattr(getattr(model, "net", None), "landmarks", 0)
    if k:
        raise InputError(f"gradients of distances are not offered for a landmark network (landmarks={k}); pass "
                         "inputs without requires_grad, or use kernels.field.landmark_distance_and_gradient in a Warp "
                         "kernel")


def distance(model, p, q, plain, **kw):
    """``plain`` (``queries.distance``) with gradients to whichever of p, q requires one (torch tensors)."""
    _no_landmarks(model)
    p = p if isinstance(p, torch.Tensor) else torch.as_tensor(np.asarray(p, np.float32), device=q.device)
    q = q if isinstance(q, torch.Tensor) else torch.as_tensor(np.asarray(q, np.float32), device=p.device)
    return _Distance.apply(_float_tensor(p, "p"), _float_tensor(q, "q"), model, kw, plain)


def ssad(model, source, plain, **kw):
    """``plain`` (``queries.ssad``) from a point source tensor (3,) with gradients to it."""
    _no_landmarks(model)
    return _Sources.apply(_float_tensor(source, "source"), model, kw, True, plain, None)


def msad(model, sources, plain, matrix, **kw):
    """``plain`` (``queries.msad``) from point sources (S, 3) with gradients to them (each vertex's to its nearest
    source, found by ``matrix``, ``queries.distance_matrix``)."""
    _no_landmarks(model)
    return _Sources.apply(_float_tensor(sources, "sources"), model, kw, False, plain, matrix)


def sdf(model, x, plain, **kw):
    """``plain`` (``queries.sdf``) with gradients to x."""
    return _Sdf.apply(_float_tensor(x, "x"), model, kw, plain)
