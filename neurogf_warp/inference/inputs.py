"""Checks and conversions of query inputs: points (numpy, torch or wp.array), sources given as vertex indices or
points, point pairs; the model's domain.

A point must be finite and inside the cube ``[-DOMAIN, DOMAIN]^3`` of the network's normalized frame, i.e. within
1.5 bounding radii of the mesh's bounding-box centre along each axis (the networks were trained on points within
[-1.01, 1.01]^3 and extrapolate without meaning beyond it). Refusals are ValueErrors that name the offending row.

Coordinates: numpy arrays and lists (host input) are made relative to the mesh centre in float64 before they
become float32 (``QueryState.frame``), so a mesh far from the origin loses nothing; torch tensors and
``wp.array``s are used as float32 mesh coordinates (``QueryState.user_frame``), the kernels subtracting the
float64 centre, so they are exact to their own float32 resolution.

One reading of every argument, for every query of both kinds of model (per-mesh and conditioned generalizable): a
*source* argument (``ssad``, ``msad``, ``distance_matrix`` sources and targets) that is integer is vertex indices in
the mesh file's numbering (a single integer or a 1-D array; a 2-D integer array is refused rather than guessed), and
float is points (S, 3); a *point* argument (``distance``, ``sdf``, ``path``, ``project``) is coordinates, (N, 3) or
(3,), of any real dtype. Torch tensors without values (the ``meta`` device) or sparse ones are refused, naming the
argument.
"""
from __future__ import annotations

import math

import numpy as np
import torch
import warp as wp

from neurogf_warp.common.arrays import _is_torch, as_array, as_points, resolve_device
from neurogf_warp.common.checks import InputError
from neurogf_warp.inference.state import DOMAIN, query_state, to_relative
from neurogf_warp.kernels.inference import finish
from neurogf_warp.model.model import Model

__all__ = ["DOMAIN", "check_domain", "check_tensor", "points_in", "sources_in", "pair_inputs", "pair_components",
           "single_answer", "check_points_in_frame"]

_NO_BAD = 2**31 - 1
_OUTSIDE = "outside the model's domain (the cube of half-side 1.5 bounding radii around the mesh's bounding-box centre)"


def check_domain(model: Model, pts: wp.array, name: str, frame, other: wp.array | None = None,
                 other_name: str = ""):
    """Refuse non-finite points and points outside the domain cube (``frame``: the points' coordinates): one device
    pass over one or two arrays and one read-back of two integers (the only synchronization a checked query
    makes)."""
    n = pts.shape[0]
    if not n:
        return
    dev = pts.device
    st = query_state(model, dev)
    bad, host = st.check_buffers
    bad.fill_(_NO_BAD)
    wp.launch(finish.check_points, n, inputs=[pts, other if other is not None else st.no_points, frame, DOMAIN,
                                              bad], device=dev)
    wp.copy(host, bad)
    if dev.is_cuda:
        wp.synchronize_stream(dev.stream)
    flags = host.numpy()
    for k, (arr, label) in enumerate(((pts, name), (other, other_name))):
        i = int(flags[k])
        if i != _NO_BAD:
            x = arr[i - 1: i].numpy()[0].astype(np.float64)
            if frame is st.frame:  # relative to the centre: report mesh coordinates
                x = x + st.center
            where = _OUTSIDE if np.all(np.isfinite(x)) else "non-finite (NaN or inf)"
            raise ValueError(f"{label}[{i - 1}] = {x.tolist()} is {where}")


def check_tensor(x, name: str) -> None:
    """Refuse a torch tensor that holds no values (on the ``meta`` device) or is sparse, naming ``name``."""
    if _is_torch(x):
        if x.is_meta:
            raise InputError(f"{name} is a torch tensor on the 'meta' device, which holds no values: pass a tensor "
                             "with data (on 'cpu' or 'cuda'), a numpy array or a list")
        if x.layout != torch.strided:
            raise InputError(f"{name} is a sparse torch tensor ({x.layout}): pass a dense one (x.to_dense())")


def check_flag(check, name: str = "check") -> None:
    """A flag argument must be a bool: a string such as "no" would read as True."""
    if not isinstance(check, (bool, np.bool_)):
        raise InputError(f"{name} must be True or False, got {check!r}")


def _on_host(x) -> bool:
    return not isinstance(x, wp.array) and not _is_torch(x)


def points_in(model: Model, x, name: str, dev, check: bool = True, host: bool | None = None):
    """(wp.array of vec3 on dev, kind, single, frame) for (N, 3) or (3,) input: host input relative to the mesh
    centre (made in float64) with ``state.frame``, device input as given with ``state.user_frame``. ``host``:
    force the host route on (True) or off (False; host input then becomes float32 mesh coordinates)."""
    check_tensor(x, name)
    check_flag(check)
    st = query_state(model, dev)
    single = _is_single_point(x)
    if host is None:
        host = _on_host(x)
    if host and _on_host(x):
        a = as_array(x, name)
        if np.issubdtype(a.dtype, np.floating) or np.issubdtype(a.dtype, np.integer):
            a = a.astype(np.float64)
            if a.ndim >= 1 and a.shape[-1] == 3:
                a = to_relative(st, a)
        arr, kind = as_points(a, name, dev, check=False, single=True)
        frame = st.frame
    else:
        arr, kind = as_points(x, name, dev, check=False, single=True)
        frame = st.user_frame
    if check:
        check_domain(model, arr, name, frame)
    return arr, kind, single, frame


def _is_single_point(x) -> bool:
    try:
        shape = tuple(x.shape) if hasattr(x, "shape") else np.shape(x)
    except ValueError:  # ragged: refused by the caller, naming the argument
        return False
    if isinstance(x, wp.array):
        return x.ndim == 1 and x.dtype != wp.vec3 and shape == (3,)
    return shape == (3,)


def sources_in(model: Model, src, name: str, dev, one: bool = False):
    """Sources as (points relative to the mesh centre (S, 3) float64, internal vertex ids or None, component labels
    or None). Vertex indices are integers, one or a 1-D list/array (S,), in the mesh file's numbering; points are
    floats of shape (S, 3), or (3,) for the one source of ``ssad`` (``one``): a flat list of floats is never read as
    points or indices by its length, and a 2-D integer array (indices or points?) is refused, for every query."""
    check_tensor(src, name)
    st = query_state(model, dev)
    if isinstance(src, (int, np.integer)) and not isinstance(src, (bool, np.bool_)) and model.mesh is not None:
        m = model.mesh  # the common single-vertex case without array machinery
        i = int(src)
        if 0 <= i < m.n_input and m.input_to_internal[i] >= 0:
            j = int(m.input_to_internal[i])
            return (st.mesh(name).rel64[j:j + 1], np.array([j]),
                    (m.internal_components[j:j + 1] if st.multi else None))
    if one and type(src) is np.ndarray and src.shape == (3,) and src.dtype.kind == "f":
        # the common single-point case: the checks below in float64 scalars, without array machinery
        rel = (src.astype(np.float64) - st.center).reshape(1, 3)
        _check_point_host(st, src, rel[0], name)
        comp = None
        if st.multi:
            pts = wp.array(rel.astype(np.float32), dtype=wp.vec3, device=dev)
            comp = st.mesh(name).components_of(pts).numpy()
        return rel, None, comp
    if isinstance(src, wp.array):
        src = src.numpy()
    elif isinstance(src, torch.Tensor):
        src = src.detach().cpu().numpy()
    try:
        a = np.asarray(src)
    except ValueError:  # ragged lists (indices mixed with points, rows of different lengths)
        a = np.asarray(None, dtype=object)
    if a.size == 0:
        raise ValueError(f"{name} is empty: give a vertex index, a list of indices or (S, 3) points")
    if a.dtype == object:  # None, an integer beyond int64, ragged lists, ...
        raise ValueError(f"{name} must be a vertex index (an integer below 2**63), a list of indices or (S, 3) points, "
                         f"got {str(src)[:80]!r}")
    if np.issubdtype(a.dtype, np.integer) or np.issubdtype(a.dtype, np.bool_):
        if np.issubdtype(a.dtype, np.bool_):
            raise TypeError(f"{name} must be vertex indices (integers) or points (floats), got booleans")
        if a.ndim > 1:  # (S, 3) integers could be 3*S indices or S points: neither reading is taken silently
            raise InputError(f"{name} is an integer array of shape {a.shape}: vertex indices are a single integer or a "
                             "1-D list/array of them (e.g. [0, 10, 200]), points are floats of shape (S, 3); for "
                             f"points write np.asarray({name}, dtype=float), for indices {name}.ravel()")
        if model.mesh is None:
            raise ValueError(f"{name} given as vertex indices, but this model has no mesh: pass points instead")
        if one and a.size != 1:
            raise ValueError(f"ssad takes one source, got {a.size}; use msad or distance_matrix for several")
        flat = a.reshape(-1)
        if flat.min() < 0:
            raise IndexError(f"{name}: vertex index {int(flat[flat < 0][0])} is negative; indices run from 0 to "
                             f"{model.mesh.n_input - 1} in the mesh file's numbering")
        ids = model.mesh.vertex(flat)
        comp = model.mesh.internal_components[ids] if st.multi else None
        return to_relative(st, model.mesh.internal_vertices[ids]), ids, comp
    if not np.issubdtype(a.dtype, np.floating):
        raise TypeError(f"{name} must be vertex indices (integers) or points (floats), got dtype {a.dtype}")
    if one:
        if a.ndim == 0:  # a float where an index was meant
            raise TypeError(f"{name}: a vertex index must be an integer, got {src!r}; a source point is 3 floats "
                            "[x, y, z]")
        if a.shape not in ((3,), (1, 3)):
            raise ValueError(f"ssad takes one source point of 3 coordinates, shape (3,), got shape {a.shape}; use "
                             "msad or distance_matrix for several")
        a = a.reshape(1, 3)
    elif a.ndim != 2 or a.shape[1] != 3:
        raise ValueError(f"{name} given as floats must be points of shape (S, 3), got shape {a.shape}: for one point "
                         "write [[x, y, z]]; vertex indices must be integers (e.g. [0, 10, 200] or an int array)")
    rel = to_relative(st, a)
    _check_domain_host(st, a, rel, name)
    comp = None
    if st.multi:
        pts = wp.array(rel.astype(np.float32), dtype=wp.vec3, device=dev)
        comp = st.mesh(name).components_of(pts).numpy()
    return rel, None, comp


def _check_domain_host(st, a: np.ndarray, rel: np.ndarray, name: str):
    """check_domain for a few points already on the host (no device round trip), in float64."""
    x = rel * float(st.frame.xscale)
    bad = ~np.all(np.isfinite(x) & (np.abs(x) <= DOMAIN), axis=1)
    if np.any(bad):
        i = int(np.argmax(bad))
        where = _OUTSIDE if np.all(np.isfinite(a[i])) else "non-finite (NaN or inf)"
        raise ValueError(f"{name}[{i}] = {a[i].tolist()} is {where}")


def _check_point_host(st, a: np.ndarray, rel: np.ndarray, name: str):
    """_check_domain_host for one point (3,), with Python floats (float64, the same arithmetic)."""
    s = float(st.frame.xscale)
    for c in rel.tolist():
        x = c * s
        if not (math.isfinite(x) and abs(x) <= DOMAIN):
            where = _OUTSIDE if np.all(np.isfinite(a)) else "non-finite (NaN or inf)"
            raise ValueError(f"{name}[0] = {a.tolist()} is {where}")


def check_points_in_frame(points: np.ndarray, center, scale: float, name: str, shape: str = "shape"):
    """The domain rule of every model, for (N, 3) float64 host points in user units and a normalized frame
    ``(x - center) * scale`` (the generalizable model's): a row outside the cube ``[-DOMAIN, DOMAIN]^3`` of the frame,
    or with a NaN or infinite coordinate, is refused with a ValueError naming it."""
    x = (np.asarray(points, np.float64) - np.asarray(center, np.float64)) * float(scale)
    bad = ~np.all(np.isfinite(x) & (np.abs(x) <= DOMAIN), axis=1)
    if np.any(bad):
        i = int(np.argmax(bad))
        a = np.asarray(points[i], np.float64)
        where = (f"outside the model's domain (the cube of half-side {DOMAIN} bounding radii around the {shape}'s "
                 f"bounding-box centre)") if np.all(np.isfinite(a)) else "non-finite (NaN or inf)"
        raise ValueError(f"{name}[{i}] = {a.tolist()} is {where}")


def pair_inputs(model, p, q, device, check: bool = True):
    """(dev, P, Q, kind, single, frame): both on the host route when both are host arrays, else both as float32
    mesh coordinates (a host array paired with a device one is rounded to float32 first)."""
    check_tensor(p, "p")
    check_tensor(q, "q")
    check_flag(check)
    dev = resolve_device(device, like=p)
    host = _on_host(p) and _on_host(q)
    P, kind, single_p, frame = points_in(model, p, "p", dev, False, host)
    Q, _, single_q, _ = points_in(model, q, "q", dev, False, host)
    if P.shape != Q.shape:
        raise ValueError(f"p and q must have the same shape (N, 3), got {P.shape[0]} and {Q.shape[0]} points")
    if check:
        check_domain(model, P, "p", frame, Q, "q")
    return dev, P, Q, kind, single_p and single_q, frame


def relative_points(model: Model, pts: wp.array, frame) -> wp.array:
    """Points in ``frame`` as points relative to the mesh centre (``state.frame``): pts itself when they are."""
    st = query_state(model, pts.device)
    if frame is st.frame or pts.shape[0] == 0:
        return pts
    out = wp.empty_like(pts)
    wp.launch(finish.shift_points, pts.shape[0], inputs=[pts, wp.vec3d(*(-st.center))], outputs=[out],
              device=pts.device)
    return out


def pair_components(model: Model, P, Q, dev, frame):
    st = query_state(model, dev)
    if not st.multi:
        return None
    md = st.mesh("distance")
    return md.components_of(relative_points(model, P, frame)), md.components_of(relative_points(model, Q, frame))


def single_answer(res, kind: str, single: bool):
    """A single query point gives a single answer (shape (), or (m, 3) for a path)."""
    if not single:
        return res
    return res[0]
