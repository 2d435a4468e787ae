"""Queries of a trained NeuroGF: geodesic distances (point pairs, SSAD, MSAD, distance matrices), SDF, paths.

Coordinates: with a mesh attached, points are in the mesh's own coordinates and distances in its units, and
per-vertex results follow the mesh file's vertex numbering (NaN for vertices no face uses). Without a mesh,
everything is in the normalized unit-sphere frame the network was trained in. Answers do not depend on where the
mesh sits: its vertices, sources and numpy/list query points are taken relative to the mesh's centre in float64
before they become float32; torch tensors and wp.arrays are float32 mesh coordinates, and the kernels subtract
the centre (in float64 in the per-thread kernels, as a float32 pair hi + lo in the tensor-core ones), so they are
exact to about their own float32 resolution (at 1e6 from the origin that is 0.06 units: pass far-away points as
float64 numpy arrays). Results are float32 (paths: float32 mesh coordinates).

What the answers mean: a geodesic distance is never shorter than the straight line between its points (so never
negative), is exactly 0 from a point to itself (and at an SSAD's source vertex), and is +inf between points of
different connected components of the mesh (a point belongs to the component of the surface point closest to
it). Points must lie in the model's domain: the cube ``[-DOMAIN, DOMAIN]^3`` of the normalized frame, i.e. within
1.5 bounding radii of the mesh's bounding-box centre along each axis (the networks were trained on points within
[-1.01, 1.01]^3 and extrapolate without meaning beyond it). With ``check=True`` (the default) a point outside it,
or a NaN or infinite coordinate, is refused with a ValueError naming the row; with ``check=False`` (no check, no
synchronization) such a row's answer is NaN (distance, sdf, every point of a path), never a number. Sources
(ssad, msad, distance_matrix) are always checked. Distances are meaningful for points on or near the surface:
the network was trained on surface points, and off-surface points inside the domain get the value of an
extrapolation. ``raw=True`` returns the network's own values: not raised to the straight line, not exactly 0 at
the source (NaN and +inf as above).

precision:
  "fp16"  tensor-core kernels (kernels/tensorcore.py): fp16 weights and activations, fp32 sums, within about
          1e-4 of a float64 evaluation relative to the largest distance. The fast path on CUDA devices.
  "fp32"  per-thread kernels (kernels/mlp.py): fp32 weights, float64 sums, within ~1e-6 of float64. On the CPU
          the fast path; on a GPU the reference. D = 512 networks always use it.
  "auto"  (default) fp16 on CUDA devices, fp32 on the CPU (where the tensor-core kernels run only as a slow
          emulation, used by the tests).

Vertex queries (ssad, msad, distance_matrix) keep the embeddings of every mesh vertex on the device after the
first call (``cache=True``): fp16 packed, 2 D bytes per vertex (223 MB for 436,000 vertices at D = 256), or fp32,
4 D bytes, for precision "fp32"; later calls then run only the distance head. ``unbind`` (or
``Model.unbind``) frees them and everything made from them.
"""
from __future__ import annotations

import time
import warnings

import numpy as np
import torch
import warp as wp

from neurogf_warp.common.arrays import Output, resolve_device
from neurogf_warp.common.checks import InputError
from neurogf_warp.inference import autograd
from neurogf_warp.inference.autograd import wants_grad
from neurogf_warp.inference.backends import PerThread, backend_of, bind, in_chunks
from neurogf_warp.inference.inputs import (DOMAIN, check_flag, check_tensor, pair_components, pair_inputs, points_in,
                                          single_answer, sources_in)
from neurogf_warp.inference.paths import PROJECT_STEPS, path, project  # noqa: F401  (public through this module)
from neurogf_warp.inference.state import PRECISIONS, check_memory, query_state, unbind
from neurogf_warp.kernels.inference import finish
from neurogf_warp.model.folded import BN_EPS, fold_batchnorm  # noqa: F401  (fold_batchnorm: public since the first release)
from neurogf_warp.model.model import Model

__all__ = ["fold_batchnorm", "warp_weights", "ssad", "msad", "distance_matrix", "distance", "sdf", "path",
           "project", "embed", "warmup", "bind", "unbind", "DOMAIN", "PRECISIONS"]

CHUNK_BYTES = 1 << 30  # device memory for one chunk of a many-source result bound for the host

_warned_unbound = set()


def warp_weights(model: Model, device=None):
    """The model's folded float32 weights on ``device`` for the per-thread ``@wp.func``s (``mlp.NeuroGFWeights``)."""
    return query_state(model, device).weights


# ---- vertex queries ---------------------------------------------------------------------------------------------------

def _vertex_distances(model: Model, src, name: str, device, output: str, precision: str, cache: bool,
                      reduce_min: bool, one: bool = False, raw: bool = False):
    st = query_state(model, device)
    dev = st.device
    be = backend_of(st, precision)
    md = st.mesh(name)
    pts, ids, comp = sources_in(model, src, name, dev, one=one)
    S, V = len(pts), md.V
    rows_out = 1 if reduce_min else S
    need = 4 * rows_out * (V + (0 if md.identity else md.n_input))
    if output == "numpy" and rows_out > 1 and need > CHUNK_BYTES:
        # a large matrix for the host: sources in chunks that fit, each copied out before the next
        step = max(1, int(CHUNK_BYTES // (need // rows_out)))
        return np.concatenate([_vertex_distances(model, src_chunk, name, dev, output, precision, cache, False,
                                                 raw=raw) for src_chunk in _source_chunks(src, pts, ids, step)])
    check_memory(dev, need, f"a ({rows_out}, {md.n_input}) result", "use output='numpy' (computed in chunks of "
                  "sources) or fewer sources per call")
    if cache and be.kept is None:
        try:
            bind(model, dev, precision)
        except MemoryError as e:  # the query still runs, embedding the vertices as it goes
            if (id(model), str(dev)) not in _warned_unbound:
                _warned_unbound.add((id(model), str(dev)))
                warnings.warn(f"{e}; answering without kept embeddings", RuntimeWarning, stacklevel=3)
    internal = wp.empty(rows_out * V, dtype=wp.float32, device=dev)
    _sources_in_chunks(be, md, pts, ids, comp, internal, reduce_min, raw)
    flat = rows_out == 1 and (one or reduce_min)
    if md.identity:
        res = internal if flat else internal.reshape((rows_out, V))
    else:
        res = wp.empty((rows_out, md.n_input), dtype=wp.float32, device=dev)
        args = {"internal": internal.reshape((rows_out, V)), "inv": md.inv, "out": res}
        if rows_out == 1:  # replayed (host time of a small query); it holds its last arrays, so only one row's
            st.launches.run(finish.to_input, res.shape, args, group="to_input")
        else:
            wp.launch(finish.to_input, res.shape, inputs=list(args.values()), device=dev)
        if flat:
            res = res.reshape(-1)
    return Output(output, dev).result(res)


def _sources_in_chunks(be, md, pts, ids, comp, internal: wp.array, reduce_min: bool, raw: bool):
    """``be.vertex_distances`` over the sources, in chunks of sources on the CPU (``in_chunks``: Ctrl-C between
    them); every source's row is its own, and the nearest source of several chunks is the least of their minima."""
    S, V = len(pts), md.V
    dev = internal.device
    if S <= 1 or not dev.is_cpu:
        be.vertex_distances(md, pts, ids, comp, internal, reduce_min, raw)
        return
    part = wp.empty(V, dtype=wp.float32, device=dev) if reduce_min else None
    done = []

    def run(lo, hi):
        sl = slice(lo, hi)
        sub = (pts[sl], None if ids is None else ids[sl], None if comp is None else comp[sl])
        if not reduce_min:
            be.vertex_distances(md, *sub, internal[lo * V: hi * V], False, raw)
            return
        be.vertex_distances(md, *sub, part if done else internal, True, raw)
        if done:  # the CPU's arrays are host memory: numpy works on them in place
            np.fmin(internal.numpy(), part.numpy(), out=internal.numpy())
        done.append(hi)

    in_chunks(dev, S, run, first=max(1, (1 << 14) // max(V, 1)), align=1)


def _generalizable(model, name: str, device, output: str, precision: str, raw: bool, cache: bool = True, **kw):
    """The answer of a generalizable model (``neurogf_warp.generalizable``) given to a per-mesh query function: its
    own method when it is conditioned on a shape, and what the per-mesh options become there; None for a per-mesh
    model. Options it does not have are refused by name; the flags are checked here for both kinds of model."""
    check_flag(raw, "raw")
    check_flag(cache, "cache")
    if isinstance(model, Model) or type(model).__module__ != "neurogf_warp.generalizable.model":
        return None
    method = getattr(model, name)
    if not hasattr(model, "wn"):  # not conditioned: the method says how to condition it
        return method()
    if device is not None and str(wp.get_device(device)) != str(model.device):
        raise InputError(f"device={device!r}: this generalizable model is conditioned on {model.device}; condition it "
                         f"on {device!r} (model.condition(shape, device=...)) or leave device out")
    if output != "numpy":
        raise InputError(f"output={output!r}: a conditioned generalizable model answers numpy arrays; use "
                         f"output='numpy' (the default)")
    if raw:
        raise InputError("raw=True is for per-mesh models; a generalizable model's answers are its own values")
    if precision not in ("auto", "fp32", "fp16"):
        raise InputError(f"precision must be one of ('auto', 'fp16', 'fp32'), got {precision!r}")
    return method(**kw, precision="fp32" if precision == "auto" else precision)


def _source_chunks(src, pts, ids, step: int):
    """The sources of a query in chunks of ``step``, in the form they came in (vertex indices or points)."""
    flat = np.asarray(ids if ids is not None else pts)
    given = np.asarray(src.numpy() if isinstance(src, wp.array) else src.detach().cpu().numpy()
                       if isinstance(src, torch.Tensor) else src)
    given = given.reshape(-1) if ids is not None else given.reshape(-1, 3)
    return [given[i:i + step] for i in range(0, len(flat), step)]


def ssad(model: Model, source, device=None, output: str = "numpy", precision: str = "auto", cache: bool = True,
         raw: bool = False):
    """Single source, all destinations: the geodesic distance from ``source`` to every mesh vertex.

    Parameters
    ----------
    source : int or (3,) float
        A vertex index in the mesh file's numbering, or a point in mesh coordinates.
    device : str, optional
        "cpu" or "cuda:N" (default: Warp's preferred device).
    output : {"numpy", "torch", "warp"}
        The kind of array returned; "torch" and "warp" stay on the device.
    precision : {"auto", "fp16", "fp32"}
        See the module docstring.
    cache : bool
        Keep every vertex's embedding on the device for later vertex queries (see the module docstring).
    raw : bool
        The network's own values: not raised to the straight-line distance, no exact 0 at the source (for parity
        checks).

    Returns
    -------
    (n_input,) float32
        Distances in mesh units, in the file's vertex numbering: NaN for vertices no face uses, +inf for vertices
        on another connected component, exactly 0 at the source vertex.
    """
    gen = _generalizable(model, "ssad", device, output, precision, raw, cache, source=source)
    if gen is not None:
        return gen
    if wants_grad(source):
        return autograd.ssad(model, source, ssad, device=device, precision=precision, cache=cache, raw=raw)
    return _vertex_distances(model, source, "source", device, output, precision, cache, False, one=True, raw=raw)


def msad(model: Model, sources, device=None, output: str = "numpy", precision: str = "auto", cache: bool = True,
         raw: bool = False):
    """Multiple sources, all destinations: the distance from every mesh vertex to its nearest source.

    sources: vertex indices (S,) in the file's numbering (integers), or points (S, 3) in mesh coordinates (floats;
    one point is [[x, y, z]]: a flat list of floats is refused, never read as a point or as indices).
    Returns (n_input,) float32, as ``ssad``.
    """
    gen = _generalizable(model, "msad", device, output, precision, raw, cache, sources=sources)
    if gen is not None:
        return gen
    if wants_grad(sources):
        return autograd.msad(model, sources, msad, distance_matrix, device=device, precision=precision, cache=cache, raw=raw)
    return _vertex_distances(model, sources, "sources", device, output, precision, cache, True, raw=raw)


def distance_matrix(model: Model, sources, targets=None, device=None, output: str = "numpy",
                    precision: str = "auto", cache: bool = True, raw: bool = False):
    """Distances from many sources at once: (S, n_input) to every mesh vertex, or (S, T) to given targets.

    Parameters
    ----------
    sources : (S,) int or (S, 3) float
        Vertex indices (the file's numbering) or points in mesh coordinates (floats must have shape (S, 3)).
    targets : None, (T,) int or (T, 3) float
        None: every mesh vertex (rows in the file's numbering, NaN columns for unused vertices). Otherwise
        vertex indices or points; each target is embedded once and shared by all sources.

    Notes
    -----
    The (S, V) form of S sources costs about S single-source queries of the distance head but one pass over the
    vertex embeddings; memory is 4 S V bytes for the result.
    """
    gen = _generalizable(model, "distance_matrix", device, output, precision, raw, cache, sources=sources,
                         targets=targets)
    if gen is not None:
        return gen
    if targets is None:
        return _vertex_distances(model, sources, "sources", device, output, precision, cache, False, raw=raw)
    st = query_state(model, device)
    dev = st.device
    be = backend_of(st, precision)
    spts, _, scomp = sources_in(model, sources, "sources", dev)
    tpts, _, tcomp = sources_in(model, targets, "targets", dev)
    S, T = len(spts), len(tpts)
    src_pos = wp.array(spts.astype(np.float32), dtype=wp.vec3, device=dev)
    tgt_pos = wp.array(tpts.astype(np.float32), dtype=wp.vec3, device=dev)
    res = wp.empty((S, T), dtype=wp.float32, device=dev)
    multi = scomp is not None and tcomp is not None
    tc_arr = wp.array(tcomp.astype(np.int32), dtype=wp.int32, device=dev) if multi else None
    sc_arr = wp.array(scomp.astype(np.int32), dtype=wp.int32, device=dev) if multi else None
    be.target_distances(src_pos, tgt_pos, sc_arr, tc_arr, res, raw)
    return Output(output, dev).result(res)


# ---- point queries ----------------------------------------------------------------------------------------------------

def distance(model: Model, p, q, device=None, precision: str = "auto", check: bool = True, raw: bool = False):
    """Geodesic distances between point pairs: (N, 3), (N, 3) -> (N,) float32, mesh units; (3,), (3,) -> ().

    Symmetric, never shorter than |p - q|, 0 for a point and itself, +inf across connected components. Arrays come
    back in the kind they came in (numpy, torch or wp.array, on the input's device). ``check``: refuse non-finite
    and out-of-domain points (one device-side pass and a synchronization); with False such rows give NaN.
    ``raw``: the network's own values (not raised to |p - q|, no exact 0 for identical points).
    """
    gen = _generalizable(model, "distance", device, "numpy", precision, raw, p=p, q=q)
    if gen is not None:
        return gen
    if wants_grad(p, q):
        return autograd.distance(model, p, q, distance, device=device, precision=precision, check=check, raw=raw)
    dev, P, Q, kind, single, frame = pair_inputs(model, p, q, device, check)
    be = backend_of(query_state(model, dev), precision)
    out = Output(kind, dev)
    res = out.empty(P.shape[0])
    n = P.shape[0]
    if n:
        in_chunks(dev, n, lambda lo, hi: be.pairs(P[lo:hi], Q[lo:hi], res[lo:hi], raw, frame))
        comps = pair_components(model, P, Q, dev, frame)
        if comps is not None:
            wp.launch(finish.split_pairs, n, inputs=[*comps, res], device=dev)
    return single_answer(out.result(res), kind, single)


def sdf(model: Model, x, device=None, precision: str = "auto", check: bool = True):
    """Signed distance from the network's SDF head: (N, 3) -> (N,) float32 mesh units, negative inside; (3,) -> ().

    ``check``: refuse non-finite and out-of-domain points; with False their rows are NaN."""
    check_tensor(x, "x")
    if wants_grad(x):
        return autograd.sdf(model, x, sdf, device=device, precision=precision, check=check)
    dev = resolve_device(device, like=x)
    X, kind, single, frame = points_in(model, x, "x", dev, check)
    be = backend_of(query_state(model, dev), precision)
    out = Output(kind, dev)
    res = out.empty(X.shape[0])
    if X.shape[0]:
        in_chunks(dev, X.shape[0], lambda lo, hi: be.sdf(X[lo:hi], res[lo:hi], frame, not check))
    return single_answer(out.result(res), kind, single)


def embed(model: Model, x, device=None, check: bool = True) -> wp.array:
    """Point embeddings e(x) of the lifting network: (N, 3) -> (N, D) float32 wp.array on the device.
    check: refuse non-finite points and points outside the model's domain (as ``sdf``; the network means nothing
    there)."""
    check_tensor(x, "x")
    dev = resolve_device(device, like=x)
    pts, _, _, frame = points_in(model, x, "x", dev, check=check)
    return PerThread(query_state(model, dev)).embed(pts, frame)


# ---- compilation --------------------------------------------------------------------------------------------------------

def warmup(model: Model, device=None, precision: str = "auto") -> dict:
    """Compile (or load from Warp's kernel cache) every kernel the queries use on ``device``, by answering one
    tiny query of each kind; nothing is kept (no vertex embeddings).

    Returns {"seconds": wall time}. Later calls in the process find the kernels loaded; a new process loads them
    from Warp's kernel cache (``wp.config.kernel_cache_dir``) in milliseconds instead of compiling.
    """
    dev = resolve_device(device)
    prec = backend_of(query_state(model, dev), precision).precision
    t0 = time.perf_counter()
    x = model.mesh.internal_vertices[:2] if model.mesh is not None else np.array([[0.1, 0.2, 0.3], [-0.3, 0.1, 0.0]])
    kw = dict(device=dev, precision=prec)
    distance(model, x[:1], x[1:], **kw)
    sdf(model, x, **kw)
    path(model, x[:1], x[1:], m=16, **kw)
    path(model, x[:1], x[1:], m=8, refine=1, project="mesh" if model.mesh is not None else "sdf", **kw)
    if model.mesh is not None:
        ssad(model, 0 if model.mesh.input_to_internal[0] >= 0 else int(model.mesh.index[0]), cache=False, **kw)
        ssad(model, x[0], cache=False, **kw)
        msad(model, x, cache=False, **kw)
    distance_matrix(model, x, x, **kw)
    wp.synchronize_device(dev)
    return {"seconds": time.perf_counter() - t0}
