"""Queries of a trained NeuroGF: geodesic distances (point pairs, SSAD, MSAD, distance matrices), SDF, paths.

Coordinates: with a mesh attached, points are in the mesh's own coordinates and distances in its units, and
per-vertex results follow the mesh file's vertex numbering (NaN for vertices no face uses). Without a mesh,
everything is in the normalized unit-sphere frame the network was trained in.

What the answers mean: a geodesic distance is never negative, is exactly 0 from a point to itself (and at an
SSAD's source vertex), and is +inf between points of different connected components of the mesh (a point
belongs to the component of the surface point closest to it). Points must lie in the model's domain: the cube
``[-DOMAIN, DOMAIN]^3`` of the normalized frame, i.e. within 1.5 bounding radii of the mesh's bounding-box centre
along each axis; farther points are refused with a ValueError (the networks were trained on points within
[-1.01, 1.01]^3 and extrapolate without meaning beyond it). Distances are meaningful for points on or near the
surface: the network was trained on surface points, and off-surface points get the value of an extrapolation.

precision:
  "fp16"  tensor-core kernels (kernels/tensorcore.py): fp16 weights and activations, fp32 sums, within about
          1e-4 of a float64 evaluation relative to the largest distance. The fast path on CUDA devices.
  "fp32"  per-thread kernels (kernels/mlp.py): fp32 weights, float64 sums, within ~1e-6 of float64. On the CPU
          the fast path; on a GPU the reference. D = 512 networks always use it.
  "auto"  (default) fp16 on CUDA devices, fp32 on the CPU (where the tensor-core kernels run only as a slow
          emulation, used by the tests).

Vertex queries (ssad, msad, distance_matrix) keep the embeddings of every mesh vertex on the device after the
first call (``cache=True``): fp16 packed, 2 D bytes per vertex (223 MB for 436,000 vertices at D = 256), or fp32,
4 D bytes, for precision "fp32"; later calls then run only the distance head. ``Model.unbind`` frees them.
"""
from __future__ import annotations

import time
import warnings

import numpy as np
import torch
import warp as wp

from .arrays import Output, as_points, resolve_device
from .engine import Engine, supported
from .folded import BN_EPS, fold_batchnorm  # noqa: F401  (fold_batchnorm: public since the first release)
from .kernels import finish, head_fp32, mlp
from .kernels import refine as refine_kernels
from .model import Model

__all__ = ["fold_batchnorm", "warp_weights", "ssad", "msad", "distance_matrix", "distance", "sdf", "path",
           "project", "embed", "warmup", "DOMAIN", "PRECISIONS"]

DOMAIN = 1.5
CHUNK_BYTES = 1 << 30  # device memory for one chunk of a many-source result bound for the host
PRECISIONS = ("auto", "fp16", "fp32")
PROJECT_STEPS = 2  # Newton steps from a point near the surface; |sdf| falls ~10x per step (a trained SDF head)


# ---- per-device state kept with the model ---------------------------------------------------------------------------

def warp_weights(model: Model, device=None) -> mlp.NeuroGFWeights:
    """The model's folded float32 weights on ``device`` for the per-thread ``@wp.func``s (cached)."""
    dev = resolve_device(device)
    key = ("weights", str(dev))
    if key not in model._warp:
        w = mlp.NeuroGFWeights()
        layers = {"l": list(model.net.lifting), "g": list(model.net.gdf_head), "s": list(model.net.sdf_head),
                  "c": [model.net.cdw_fc], "p": list(model.net.spf_head)}
        for prefix, mods in layers.items():
            for i, layer in enumerate(mods):
                W, b = fold_batchnorm(layer)
                name = f"{prefix}{i}" if prefix != "c" else "c"
                setattr(w, f"{name}_w", wp.array(W.astype(np.float32), dtype=wp.float32, device=dev))
                if b is not None:
                    setattr(w, f"{name}_b", wp.array(b.astype(np.float32), dtype=wp.float32, device=dev))
        w.euclid = 1.0 if model.net.euclid else 0.0
        w.residual = 1.0 if model.net.path_residual else 0.0
        w.window = 1.0 if model.net.path_window else 0.0
        model._warp[key] = w
    return model._warp[key]


def _frame(model: Model) -> mlp.Frame:
    """The model's user -> network frame as the kernels take it (made once per model)."""
    f = model._warp.get("frame")
    if f is None:
        f = model._warp["frame"] = _make_frame(model)
    return f


def _make_frame(model: Model) -> mlp.Frame:
    f = mlp.Frame()
    if model.in_mesh_frame:
        f.center = wp.vec3(*model.center.astype(np.float32))
        f.xscale = float(model.scale)
        f.dscale = float(1.0 / model.scale)
    else:
        f.center = wp.vec3(0.0, 0.0, 0.0)
        f.xscale = 1.0
        f.dscale = 1.0
    return f


def _engine(model: Model, dev) -> Engine:
    key = ("engine", str(dev))
    if key not in model._warp:
        model._warp[key] = Engine(model.net, _frame(model), dev)
    return model._warp[key]


def _precision(model: Model, precision: str, dev) -> str:
    if precision not in PRECISIONS:
        raise ValueError(f"precision must be one of {PRECISIONS}, got {precision!r}")
    if precision == "auto":
        return "fp16" if dev.is_cuda and supported(model.net) else "fp32"
    if precision == "fp16" and not supported(model.net):
        raise ValueError(f"precision='fp16' supports D in (64, 128, 256), this network has D={model.D}: "
                         "use precision='fp32'")
    return precision


class _MeshOnDevice:
    """The mesh's internal vertices (user frame, float32), component labels and numbering map on one device."""

    def __init__(self, model: Model, dev):
        m = model.mesh
        self.V, self.n_input = len(m.vertices), m.n_input
        self.verts = wp.array(m.vertices.astype(np.float32), dtype=wp.vec3, device=dev)
        self.multi = m.n_components > 1
        self.comp = wp.array(m.components.astype(np.int32), dtype=wp.int32, device=dev) if self.multi else None
        inv = m.input_to_internal
        self.identity = self.n_input == self.V and bool(np.array_equal(inv, np.arange(self.V)))
        self.inv = None if self.identity else wp.array(inv.astype(np.int32), dtype=wp.int32, device=dev)
        self._wp_mesh = None
        self._face_comp = None
        self.dev = dev

    def lifted_rows(self, eng: Engine):
        """The vertices as rows embedded inside the kernels (no kept embeddings)."""
        if getattr(self, "_lifted", None) is None:
            self._lifted = eng.rows(self.verts, None, self.comp)
        return self._lifted

    def components_of(self, pts: wp.array) -> wp.array:
        """Component label of each point (that of its closest surface point)."""
        if self._wp_mesh is None:
            raise RuntimeError("components_of needs the Warp mesh: call with the model")
        out = wp.empty(pts.shape[0], dtype=wp.int32, device=self.dev)
        if pts.shape[0]:
            wp.launch(finish.point_components, pts.shape[0], inputs=[self._wp_mesh.id, pts, self._face_comp],
                      outputs=[out], device=self.dev)
        return out


def _mesh_data(model: Model, dev, what: str) -> _MeshOnDevice:
    if model.mesh is None:
        raise ValueError(f"{what} needs the model's mesh: load the model with neurogf_warp.load(path, mesh=...)")
    key = ("mesh", str(dev))
    if key not in model._warp:
        model._warp[key] = _MeshOnDevice(model, dev)
    md = model._warp[key]
    if md.multi and md._wp_mesh is None:
        m = model.mesh
        md._wp_mesh = wp.Mesh(points=md.verts, indices=wp.array(m.faces.reshape(-1).astype(np.int32), device=dev))
        md._face_comp = wp.array(m.components[m.faces[:, 0]].astype(np.int32), dtype=wp.int32, device=dev)
    return md


def _binding(model: Model, dev, precision: str):
    return model._warp.get(("bound", str(dev), precision))


def bind(model: Model, device=None, precision: str = "auto") -> int:
    """Embed every mesh vertex once and keep the result on ``device`` for later vertex queries; returns bytes kept.

    fp16: packed (V, D/2) uint32, 2 D bytes per vertex; fp32: (V, D) float32, 4 D bytes per vertex.
    """
    dev = resolve_device(device)
    prec = _precision(model, precision, dev)
    md = _mesh_data(model, dev, "binding")
    b = _binding(model, dev, prec)
    if b is None:
        need = md.V * model.D * (2 if prec == "fp16" else 4)
        _check_memory(dev, need, f"keeping the embeddings of {md.V:,} vertices ({need / 1e6:.0f} MB)",
                      "query with cache=False (every call then embeds the vertices) or free GPU memory", 0.5)
        if prec == "fp16":
            b = _engine(model, dev).embed(md.verts)
        else:
            b = embed(model, md.verts, device=dev)
        model._warp[("bound", str(dev), prec)] = b
    return int(b.capacity)


def _check_memory(dev, need: int, what: str, hint: str, share: float = 0.9):
    """MemoryError, with the sizes and what to do, when ``need`` bytes exceed ``share`` of the device's free memory."""
    if not dev.is_cuda:
        return
    free = getattr(dev, "free_memory", None)
    if free and need > share * free:
        raise MemoryError(f"{what} needs {need / 1e9:.2f} GB, but {free / 1e9:.2f} GB is free on {dev}: {hint}")


_warned_unbound = set()


def unbind(model: Model, device=None) -> None:
    """Free the vertex embeddings kept on ``device`` (all devices when None)."""
    for key in [k for k in model._warp if k[0] == "bound" and (device is None or k[1] == str(resolve_device(device)))]:
        del model._warp[key]


# ---- inputs ---------------------------------------------------------------------------------------------------------

_NO_BAD = 2**31 - 1


def _check_domain(model: Model, pts: wp.array, name: str, other: wp.array | None = None, other_name: str = ""):
    """Refuse non-finite points and points outside the domain cube: one device pass over one or two arrays and
    one read-back of two integers (the only synchronization a checked query makes)."""
    n = pts.shape[0]
    if not n:
        return
    dev = pts.device
    key = ("check", str(dev))
    if key not in model._warp:
        model._warp[key] = (wp.empty(2, dtype=wp.int32, device=dev),
                            wp.empty(2, dtype=wp.int32, device="cpu", pinned=dev.is_cuda))
    bad, host = model._warp[key]
    bad.fill_(_NO_BAD)
    wp.launch(finish.check_points, n, inputs=[pts, other if other is not None else _empty_vec3(model, dev),
                                              _frame(model), DOMAIN, bad], device=dev)
    wp.copy(host, bad)
    if dev.is_cuda:
        wp.synchronize_stream(dev.stream)
    flags = host.numpy()
    for k, (arr, label) in enumerate(((pts, name), (other, other_name))):
        i = int(flags[k])
        if i != _NO_BAD:
            x = arr[i - 1: i].numpy()[0]
            where = ("outside the model's domain (the cube of half-side 1.5 bounding radii around the mesh's "
                     "bounding-box centre)") if np.all(np.isfinite(x)) else "non-finite (NaN or inf)"
            raise ValueError(f"{label}[{i - 1}] = {x.tolist()} is {where}")


def _empty_vec3(model: Model, dev) -> wp.array:
    key = ("no_points", str(dev))
    if key not in model._warp:
        model._warp[key] = wp.empty(0, dtype=wp.vec3, device=dev)
    return model._warp[key]


def _points(model: Model, x, name: str, dev, check: bool = True):
    """(wp.array of vec3 on dev, kind, single) for (N, 3) or (3,) input."""
    single = _is_single_point(x)
    arr, kind = as_points(x, name, dev, check=False, single=True)
    if check:
        _check_domain(model, arr, name)
    return arr, kind, single


def _is_single_point(x) -> bool:
    shape = tuple(x.shape) if hasattr(x, "shape") else np.shape(x)
    if isinstance(x, wp.array):
        return x.ndim == 1 and x.dtype != wp.vec3 and shape == (3,)
    return shape == (3,)


def _sources(model: Model, src, name: str, dev, one: bool = False):
    """Sources as (user-frame points (S, 3) float64, internal vertex ids or None, component labels or None)."""
    if isinstance(src, (int, np.integer)) and not isinstance(src, (bool, np.bool_)) and model.mesh is not None:
        m = model.mesh  # the common single-vertex case without array machinery
        i = int(src)
        if 0 <= i < m.n_input and m.input_to_internal[i] >= 0:
            j = int(m.input_to_internal[i])
            return m.vertices[j:j + 1], np.array([j]), (m.components[j:j + 1] if m.n_components > 1 else None)
    if isinstance(src, wp.array):
        src = src.numpy()
    elif isinstance(src, torch.Tensor):
        src = src.detach().cpu().numpy()
    a = np.asarray(src)
    if a.dtype == object or a.size == 0:
        raise ValueError(f"{name} is empty: give a vertex index, a list of indices or (S, 3) points")
    if np.issubdtype(a.dtype, np.integer) or np.issubdtype(a.dtype, np.bool_):
        if np.issubdtype(a.dtype, np.bool_):
            raise TypeError(f"{name} must be vertex indices (integers) or points (floats), got booleans")
        if model.mesh is None:
            raise ValueError(f"{name} given as vertex indices, but this model has no mesh: pass points instead")
        if one and a.size != 1:
            raise ValueError(f"ssad takes one source, got {a.size}; use msad or distance_matrix for several")
        flat = a.reshape(-1)
        if flat.min() < 0:
            raise IndexError(f"{name}: vertex index {int(flat[flat < 0][0])} is negative; indices run from 0 to "
                             f"{model.mesh.n_input - 1} in the mesh file's numbering")
        ids = model.mesh.vertex(flat)
        comp = model.mesh.components[ids] if model.mesh.n_components > 1 else None
        return model.mesh.vertices[ids], ids, comp
    if not np.issubdtype(a.dtype, np.floating):
        raise TypeError(f"{name} must be vertex indices (integers) or points (floats), got dtype {a.dtype}")
    if one and a.size != 3:
        raise ValueError(f"ssad takes one source point of 3 coordinates, got shape {a.shape}")
    a = a.reshape(1, 3) if a.shape == (3,) else a
    if a.ndim != 2 or a.shape[1] != 3:
        raise ValueError(f"{name} must be vertex indices or points of shape (S, 3), got shape {np.shape(src)}")
    _check_domain_host(model, a, name)
    comp = None
    if model.mesh is not None and model.mesh.n_components > 1:
        pts = wp.array(a.astype(np.float32), dtype=wp.vec3, device=dev)
        comp = _mesh_data(model, dev, name).components_of(pts).numpy()
    return a.astype(np.float64), None, comp


def _check_domain_host(model: Model, a: np.ndarray, name: str):
    """_check_domain for a few points already on the host (no device round trip)."""
    f = _frame(model)
    x = (a.astype(np.float32) - np.array(f.center, dtype=np.float32)) * np.float32(f.xscale)
    bad = ~np.all(np.isfinite(x) & (np.abs(x) <= DOMAIN), axis=1)
    if np.any(bad):
        i = int(np.argmax(bad))
        where = ("outside the model's domain (the cube of half-side 1.5 bounding radii around the mesh's "
                 "bounding-box centre)") if np.all(np.isfinite(a[i])) else "non-finite (NaN or inf)"
        raise ValueError(f"{name}[{i}] = {a[i].tolist()} is {where}")


# ---- vertex queries ---------------------------------------------------------------------------------------------------

def _vertex_distances(model: Model, src, name: str, device, output: str, precision: str, cache: bool,
                      reduce_min: bool, one: bool = False, raw: bool = False):
    dev = resolve_device(device)
    prec = _precision(model, precision, dev)
    md = _mesh_data(model, dev, name)
    pts, ids, comp = _sources(model, src, name, dev, one=one)
    S, V = len(pts), md.V
    rows_out = 1 if reduce_min else S
    need = 4 * rows_out * (V + (0 if md.identity else md.n_input))
    if output == "numpy" and rows_out > 1 and need > CHUNK_BYTES:
        # a large matrix for the host: sources in chunks that fit, each copied out before the next
        step = max(1, int(CHUNK_BYTES // (need // rows_out)))
        return np.concatenate([_vertex_distances(model, src_chunk, name, dev, output, precision, cache, False,
                                                 raw=raw) for src_chunk in _source_chunks(src, pts, ids, step)])
    _check_memory(dev, need, f"a ({rows_out}, {md.n_input}) result", "use output='numpy' (computed in chunks of "
                  "sources) or fewer sources per call")
    if cache:
        try:
            bind(model, dev, prec)
        except MemoryError as e:  # the query still runs, embedding the vertices as it goes
            if (id(model), str(dev)) not in _warned_unbound:
                _warned_unbound.add((id(model), str(dev)))
                warnings.warn(f"{e}; answering without kept embeddings", RuntimeWarning, stacklevel=3)
    bound = _binding(model, dev, prec)
    internal = wp.empty(rows_out * V, dtype=wp.float32, device=dev)
    if prec == "fp16":
        eng = _engine(model, dev)
        kw = dict(count=S, reduce_min=reduce_min, raw=raw)
        if bound is not None and ids is not None:  # rows of the kept tables: nothing to embed or copy
            rows, table = _bound_tables(model, dev, md, bound)
            if S == 1:
                eng.distances(rows, table, internal, V, row0=int(ids[0]), **kw)
            else:
                eng.distances(rows, table, internal, V, ids=wp.array(ids.astype(np.int32), dtype=wp.int32,
                                                                      device=dev), **kw)
        else:
            src_pos = wp.array(pts.astype(np.float32), dtype=wp.vec3, device=dev)
            src_comp = wp.array(comp.astype(np.int32), dtype=wp.int32, device=dev) if comp is not None else None
            rows = _bound_tables(model, dev, md, bound)[0] if bound is not None else md.lifted_rows(eng)
            eng.distances(rows, eng.sources(eng.embed(src_pos), src_pos, src_comp), internal, V, **kw)
    else:
        src_pos = wp.array(pts.astype(np.float32), dtype=wp.vec3, device=dev)
        src_comp = wp.array(comp.astype(np.int32), dtype=wp.int32, device=dev) if comp is not None else None
        head = _head_values_fp32(model, dev, md, src_pos, bound)
        full = internal.reshape((rows_out, V)) if not reduce_min else wp.empty((S, V), dtype=wp.float32, device=dev)
        none = wp.empty(0, dtype=wp.int32, device=dev)
        wp.launch(finish.finish_rows, (S, V), inputs=[head, md.verts, md.comp if md.multi else none, src_pos,
                                                      src_comp if src_comp is not None else none, _frame(model),
                                                      1.0 if model.net.euclid else 0.0, int(raw)], outputs=[full],
                  device=dev)
        if reduce_min:
            wp.launch(finish.min_rows, V, inputs=[full], outputs=[internal], device=dev)
    flat = rows_out == 1 and (one or reduce_min)
    if md.identity:
        res = internal if flat else internal.reshape((rows_out, V))
    else:
        res = wp.empty((rows_out, md.n_input), dtype=wp.float32, device=dev)
        wp.launch(finish.to_input, res.shape, inputs=[internal.reshape((rows_out, V)), md.inv], outputs=[res],
                  device=dev)
        if flat:
            res = res.reshape(-1)
    return Output(output, dev).result(res)


def _source_chunks(src, pts, ids, step: int):
    """The sources of a query in chunks of ``step``, in the form they came in (vertex indices or points)."""
    flat = np.asarray(ids if ids is not None else pts)
    given = np.asarray(src.numpy() if isinstance(src, wp.array) else src.detach().cpu().numpy()
                       if isinstance(src, torch.Tensor) else src)
    given = given.reshape(-1) if ids is not None else given.reshape(-1, 3)
    return [given[i:i + step] for i in range(0, len(flat), step)]


def _bound_tables(model: Model, dev, md, bound):
    """(rows, sources) tables of a bound model's vertices for the tensor-core kernels (made once per binding)."""
    key = ("bound_tables", str(dev))
    t = model._warp.get(key)
    if t is None or t[0] is not bound:
        eng = _engine(model, dev)
        t = (bound, eng.rows(md.verts, bound, md.comp), eng.sources(bound, md.verts, md.comp))
        model._warp[key] = t
    return t[1], t[2]


def _head_values_fp32(model: Model, dev, md: _MeshOnDevice, src_pos: wp.array, bound) -> wp.array:
    """(S, V) distance-head values (network frame, no |x - s| term) from float32 per-thread or tile kernels."""
    S, V = src_pos.shape[0], md.V
    es = embed(model, src_pos, device=dev)
    head = wp.empty((S, V), dtype=wp.float32, device=dev)
    w = warp_weights(model, dev)
    if bound is None or model.D > head_fp32.MAX_D:
        wp.launch(head_fp32.head_rows, (S, V), inputs=[_head_only(model, dev), es, src_pos, md.verts, _frame(model)],
                  outputs=[head], device=dev)
        return head
    key = ("tile_head", str(dev))
    if key not in model._warp:  # the tile kernel takes biases as (H, 1) columns
        col = lambda b: wp.array(b.numpy().reshape(-1, 1), dtype=wp.float32, device=dev)
        model._warp[key] = (w.g0_w, col(w.g0_b), w.g1_w, col(w.g1_b), w.g2_w)
    weights = model._warp[key]
    H, D = weights[0].shape
    kernel = head_fp32.head_kernel(D, H, False, head_fp32.BLOCK, head_fp32.CHUNK)
    for s in range(S):
        wp.launch_tiled(kernel, dim=[(V + head_fp32.BLOCK - 1) // head_fp32.BLOCK],
                        inputs=[es[s: s + 1], bound, *weights, D // head_fp32.CHUNK], outputs=[head[s: s + 1]],
                        block_dim=head_fp32.THREADS, device=dev)
    return head


def _head_only(model: Model, dev) -> mlp.NeuroGFWeights:
    """The folded weights with the |x - s| term switched off: raw head values for kernels.finish."""
    key = ("head_weights", str(dev))
    if key not in model._warp:
        w, h = warp_weights(model, dev), mlp.NeuroGFWeights()
        for name in mlp.NeuroGFWeights.vars:
            setattr(h, name, getattr(w, name))
        h.euclid = 0.0
        model._warp[key] = h
    return model._warp[key]


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
        The network's own values: no clamping at 0 and no exact 0 at the source (for parity checks).

    Returns
    -------
    (n_input,) float32
        Distances in mesh units, in the file's vertex numbering: NaN for vertices no face uses, +inf for vertices
        on another connected component, exactly 0 at the source vertex.
    """
    return _vertex_distances(model, source, "source", device, output, precision, cache, False, one=True, raw=raw)


def msad(model: Model, sources, device=None, output: str = "numpy", precision: str = "auto", cache: bool = True,
         raw: bool = False):
    """Multiple sources, all destinations: the distance from every mesh vertex to its nearest source.

    sources: vertex indices (S,) in the file's numbering, or points (S, 3) in mesh coordinates.
    Returns (n_input,) float32, as ``ssad``.
    """
    return _vertex_distances(model, sources, "sources", device, output, precision, cache, True, raw=raw)


def distance_matrix(model: Model, sources, targets=None, device=None, output: str = "numpy",
                    precision: str = "auto", cache: bool = True, raw: bool = False):
    """Distances from many sources at once: (S, n_input) to every mesh vertex, or (S, T) to given targets.

    Parameters
    ----------
    sources : (S,) int or (S, 3) float
        Vertex indices (the file's numbering) or points in mesh coordinates.
    targets : None, (T,) int or (T, 3) float
        None: every mesh vertex (rows in the file's numbering, NaN columns for unused vertices). Otherwise
        vertex indices or points; each target is embedded once and shared by all sources.

    The (S, V) form of S sources costs about S single-source queries of the distance head but one pass over the
    vertex embeddings; memory is 4 S V bytes for the result.
    """
    if targets is None:
        return _vertex_distances(model, sources, "sources", device, output, precision, cache, False, raw=raw)
    dev = resolve_device(device)
    prec = _precision(model, precision, dev)
    spts, _, scomp = _sources(model, sources, "sources", dev)
    tpts, _, tcomp = _sources(model, targets, "targets", dev)
    S, T = len(spts), len(tpts)
    src_pos = wp.array(spts.astype(np.float32), dtype=wp.vec3, device=dev)
    tgt_pos = wp.array(tpts.astype(np.float32), dtype=wp.vec3, device=dev)
    res = wp.empty((S, T), dtype=wp.float32, device=dev)
    multi = scomp is not None and tcomp is not None
    tc_arr = wp.array(tcomp.astype(np.int32), dtype=wp.int32, device=dev) if multi else None
    sc_arr = wp.array(scomp.astype(np.int32), dtype=wp.int32, device=dev) if multi else None
    if prec == "fp16":
        eng = _engine(model, dev)
        eng.distances(eng.rows(tgt_pos, eng.embed(tgt_pos), tc_arr), eng.sources(eng.embed(src_pos), src_pos, sc_arr),
                      res.reshape(-1), T, count=S, raw=raw)
    else:
        es = embed(model, src_pos, device=dev)
        head = wp.empty((S, T), dtype=wp.float32, device=dev)
        wp.launch(head_fp32.head_rows, (S, T), inputs=[_head_only(model, dev), es, src_pos, tgt_pos, _frame(model)],
                  outputs=[head], device=dev)
        none = wp.empty(0, dtype=wp.int32, device=dev)
        wp.launch(finish.finish_rows, (S, T), inputs=[head, tgt_pos, tc_arr if multi else none, src_pos,
                                                      sc_arr if multi else none, _frame(model),
                                                      1.0 if model.net.euclid else 0.0, int(raw)], outputs=[res],
                  device=dev)
    return Output(output, dev).result(res)


# ---- point queries ----------------------------------------------------------------------------------------------------

def _pair_inputs(model, p, q, device, check: bool = True):
    dev = resolve_device(device, like=p)
    P, kind, single_p = _points(model, p, "p", dev, False)
    Q, _, single_q = _points(model, q, "q", dev, False)
    if P.shape != Q.shape:
        raise ValueError(f"p and q must have the same shape (N, 3), got {P.shape[0]} and {Q.shape[0]} points")
    if check:
        _check_domain(model, P, "p", Q, "q")
    return dev, P, Q, kind, single_p and single_q


def _pair_components(model: Model, P, Q, dev):
    if model.mesh is None or model.mesh.n_components == 1:
        return None
    md = _mesh_data(model, dev, "distance")
    return md.components_of(P), md.components_of(Q)


def _single(res, kind: str, single: bool):
    """A single query point gives a single answer (shape (), or (m, 3) for a path)."""
    if not single:
        return res
    return res[0]


def distance(model: Model, p, q, device=None, precision: str = "auto", check: bool = True, raw: bool = False):
    """Geodesic distances between point pairs: (N, 3), (N, 3) -> (N,) float32, mesh units; (3,), (3,) -> ().

    Symmetric, never negative, 0 for a point and itself, +inf across connected components. Arrays come back in
    the kind they came in (numpy, torch or wp.array, on the input's device). ``check``: refuse non-finite and
    out-of-domain points (one device-side pass and a synchronization; with False such rows give NaN instead).
    ``raw``: the network's own values (no clamping at 0, no exact 0 for identical points).
    """
    dev, P, Q, kind, single = _pair_inputs(model, p, q, device, check)
    prec = _precision(model, precision, dev)
    out = Output(kind, dev)
    res = out.empty(P.shape[0])
    n = P.shape[0]
    if n:
        if prec == "fp16":
            _engine(model, dev).pairs(P, Q, res, raw)
        else:
            wp.launch(mlp.distance_pairs, n, inputs=[warp_weights(model, dev), P, Q, _frame(model)], outputs=[res],
                      device=dev)
            if not raw:
                wp.launch(finish.clamp_pairs, n, inputs=[P, Q, res], device=dev)
        comps = _pair_components(model, P, Q, dev)
        if comps is not None:
            wp.launch(finish.split_pairs, n, inputs=[*comps, res], device=dev)
    return _single(out.result(res), kind, single)


def sdf(model: Model, x, device=None, precision: str = "auto", check: bool = True):
    """Signed distance from the network's SDF head: (N, 3) -> (N,) float32 mesh units, negative inside; (3,) -> ()."""
    dev = resolve_device(device, like=x)
    X, kind, single = _points(model, x, "x", dev, check)
    prec = _precision(model, precision, dev)
    out = Output(kind, dev)
    res = out.empty(X.shape[0])
    if X.shape[0]:
        if prec == "fp16":
            _engine(model, dev).sdf(X, res)
        else:
            wp.launch(mlp.signed_distances, X.shape[0], inputs=[warp_weights(model, dev), X, _frame(model)],
                      outputs=[res], device=dev)
    return _single(out.result(res), kind, single)


def embed(model: Model, x, device=None) -> wp.array:
    """Point embeddings e(x) of the lifting network: (N, 3) -> (N, D) float32 wp.array on the device."""
    dev = resolve_device(device, like=x)
    pts, _ = as_points(x, "x", dev, check=False, single=True)
    out = wp.empty((pts.shape[0], model.D), dtype=wp.float32, device=dev)
    if pts.shape[0]:
        wp.launch(mlp.embed_points, pts.shape[0], inputs=[warp_weights(model, dev), pts, _frame(model)],
                  outputs=[out], device=dev)
    return out


def path(model: Model, p, q, m: int = 128, refine: int = 0, project: str | None = None, return_faces: bool = False,
         device=None, precision: str = "auto", check: bool = True):
    """Shortest paths as m points each (ends included): (N, 3), (N, 3) -> (N, m, 3) float32 mesh coordinates.

    Straight-line samples between p and q go through the network's path head, which moves them onto the
    surface. With a windowed path head (``path_window``) the ends are exactly p and q, else the network's.
    Paths between different connected components are NaN rows. A single pair (3,), (3,) gives (m, 3).

    refine > 0 shortens the paths on the SDF head's surface: that many sweeps (each inner point to the
    projected midpoint of its neighbours, ends pinned to p and q) at m/4, then m/2, then m points, from
    three starts: the head's path p -> q, its path q -> p, and the straight line; the shortest result that
    does not jump between sheets is kept. 25-50 sweeps suffice for m=128 (benchmarks/RESULTS.md); a sweep
    costs about as much as four SDF queries per point. With precision "fp16" the SDF values come from batched
    tensor-core launches (points end within ~2e-4 of the SDF surface, normalized frame; fp32: ~2e-5).

    project: None (the points as computed), "sdf" (every point moved onto the SDF head's surface by Newton steps:
    mesh-free) or "mesh" (every point snapped to the exact closest point of the mesh, ``surface.snap_to_mesh``).
    return_faces (with project="mesh"): also return, per point, the face it lies on ((N, m) int32, rows of the
    mesh's face list as given) and its barycentric coordinates ((N, m, 3) float32): (points, faces, bary).
    """
    if project not in (None, "sdf", "mesh"):
        raise ValueError(f"project must be None, 'sdf' or 'mesh', got {project!r}")
    if return_faces and project != "mesh":
        raise ValueError("return_faces=True needs project='mesh' (faces are those of the mesh)")
    if project == "mesh" and model.mesh is None:
        raise ValueError("project='mesh' needs the model's mesh: load it with neurogf_warp.load(path, mesh=...), or "
                         "use project='sdf'")
    if not isinstance(m, (int, np.integer)) or isinstance(m, bool) or m < 2:
        raise ValueError(f"m (points per path) must be an integer >= 2, got {m!r}")
    if not isinstance(refine, (int, np.integer)) or isinstance(refine, bool) or refine < 0:
        raise ValueError(f"refine (shortening sweeps) must be an integer >= 0, got {refine!r}")
    dev, P, Q, kind, single = _pair_inputs(model, p, q, device, check)
    prec = _precision(model, precision, dev)
    n, m = P.shape[0], int(m)
    out = Output(kind, dev)
    res = out.empty((n, m), dtype=wp.vec3)
    if n and not refine:
        if prec == "fp16":
            _engine(model, dev).paths(P, Q, res)
        else:
            _head_paths(model, P, Q, res, dev)
    elif n:
        _refined_paths(model, P, Q, res, int(refine), dev, prec)
    if n and project == "sdf":
        flat = res.reshape(-1)
        wp.launch(mlp.project_points, flat.shape[0], inputs=[warp_weights(model, dev), flat, _frame(model),
                                                             2 * PROJECT_STEPS], outputs=[flat], device=dev)
    faces = None
    if n and project == "mesh":
        from .surface import snap_to_mesh

        snapped, faces, bary = snap_to_mesh(model, res, device=dev)
        wp.copy(res, snapped)
    if n:
        comps = _pair_components(model, P, Q, dev)
        if comps is not None:
            wp.launch(finish.split_paths, (n, m), inputs=[*comps, res], device=dev)
    if kind == "torch":
        r = wp.to_torch(res).view(n, m, 3)
    elif kind == "warp":
        r = res
    else:
        r = res.numpy()
    if return_faces:
        conv = (lambda a: wp.to_torch(a)) if kind == "torch" else (lambda a: a) if kind == "warp" else \
            (lambda a: a.numpy())
        f, b = conv(faces.reshape((n, m))), conv(bary.reshape((n, m)))
        if kind == "torch":
            b = b.view(n, m, 3)
        return (r[0], f[0], b[0]) if single else (r, f, b)
    return r[0] if single else r


def _refined_paths(model: Model, P, Q, res, refine: int, dev, prec: str):
    n, m = res.shape
    levels = _levels(m)
    cand = wp.empty((3 * n, levels[0]), dtype=wp.vec3, device=dev)
    if prec == "fp16":
        eng = _engine(model, dev)
        eng.paths(P, Q, cand[:n])
        eng.paths(Q, P, cand[n:2 * n])
    else:
        _head_paths(model, P, Q, cand[:n], dev)
        _head_paths(model, Q, P, cand[n:2 * n], dev)
    wp.launch(mlp.straight_paths, (n, levels[0]), inputs=[P, Q], outputs=[cand[2 * n:]], device=dev)
    starts, ends = wp.empty(3 * n, dtype=wp.vec3, device=dev), wp.empty(3 * n, dtype=wp.vec3, device=dev)
    for c, (a, b) in enumerate(((P, Q), (Q, P), (P, Q))):
        wp.copy(starts, a, dest_offset=c * n, count=n)
        wp.copy(ends, b, dest_offset=c * n, count=n)
    if prec == "fp16":
        # the same schedule with batched tensor-core SDF evaluations (kernels/refine.py)
        h = refine_kernels.FD_STEP / (model.scale if model.in_mesh_frame else 1.0)
        scratch = {}
        for level, ml in enumerate(levels):
            if level:
                finer = wp.empty((3 * n, ml), dtype=wp.vec3, device=dev)
                wp.launch(mlp.resample_paths, finer.shape, inputs=[cand], outputs=[finer], device=dev)
                cand = finer
            cand = wp.clone(eng.newton_steps(cand, starts, ends, PROJECT_STEPS, False, h, scratch))
            for _ in range(refine):
                cand = eng.newton_steps(cand, starts, ends, 1, True, h, scratch)
        cand = eng.newton_steps(cand, starts, ends, 2 * PROJECT_STEPS, False, h, scratch)
    else:
        w, frame = warp_weights(model, dev), _frame(model)
        for level, ml in enumerate(levels):
            if level:
                finer = wp.empty((3 * n, ml), dtype=wp.vec3, device=dev)
                wp.launch(mlp.resample_paths, finer.shape, inputs=[cand], outputs=[finer], device=dev)
                cand = finer
            wp.launch(mlp.pin_and_project, cand.shape, inputs=[w, starts, ends, frame, PROJECT_STEPS],
                      outputs=[cand], device=dev)
            tmp = wp.empty_like(cand)
            for _ in range(refine):
                wp.launch(mlp.relax_paths, cand.shape, inputs=[w, cand, frame, 1], outputs=[tmp], device=dev)
                cand, tmp = tmp, cand
        # a sweep takes one Newton step from the midpoint; at a crease the chord's midpoint lies deeper than
        # one step reaches, so the result gets a full projection
        wp.launch(mlp.pin_and_project, cand.shape, inputs=[w, starts, ends, frame, 2 * PROJECT_STEPS],
                  outputs=[cand], device=dev)
    rev = wp.array([0, 1, 0], dtype=wp.int32, device=dev)
    wp.launch(mlp.pick_shortest, (n, m), inputs=[cand, 3, rev], outputs=[res], device=dev)


def _levels(m: int) -> list:
    """Point counts of the coarse-to-fine refinement: m/4, m/2, m (none under 8). Jacobi sweeps straighten a
    chain of k points in ~k^2 sweeps; the coarse levels do the long-range part cheaply."""
    out = [m]
    while len(out) < 3 and out[0] // 2 >= 8:
        out.insert(0, out[0] // 2)
    return out


def _head_paths(model: Model, P: wp.array, Q: wp.array, res: wp.array, dev):
    """The path head's points into res (N, m), float32 per-thread kernels."""
    n = P.shape[0]
    w = warp_weights(model, dev)
    e = wp.empty((2 * n, model.D), dtype=wp.float32, device=dev)
    frame = _frame(model)
    wp.launch(mlp.embed_points, n, inputs=[w, P, frame], outputs=[e[:n]], device=dev)
    wp.launch(mlp.embed_points, n, inputs=[w, Q, frame], outputs=[e[n:]], device=dev)
    g = wp.empty((n, model.D), dtype=wp.float32, device=dev)
    pre = wp.empty((n, w.p0_w.shape[0]), dtype=wp.float32, device=dev)
    wp.launch(mlp.path_guidance, (n, model.D), inputs=[w, e, n], outputs=[g], device=dev)
    wp.launch(mlp.path_first_layer, pre.shape, inputs=[w, g], outputs=[pre], device=dev)
    wp.launch(mlp.path_points, res.shape, inputs=[w, P, Q, pre, frame], outputs=[res], device=dev)


def project(model: Model, x, steps: int = PROJECT_STEPS, device=None):
    """Points moved onto the surface of the network's SDF head (Newton steps on its zero level set): (N, 3) -> (N, 3)."""
    if not isinstance(steps, (int, np.integer)) or isinstance(steps, bool) or steps < 0:
        raise ValueError(f"steps must be an integer >= 0, got {steps!r}")
    dev = resolve_device(device, like=x)
    X, kind, single = _points(model, x, "x", dev)
    out = Output(kind, dev)
    res = out.empty(X.shape[0], dtype=wp.vec3)
    if X.shape[0]:
        wp.launch(mlp.project_points, X.shape[0], inputs=[warp_weights(model, dev), X, _frame(model), int(steps)],
                  outputs=[res], device=dev)
    if kind == "torch":
        r = wp.to_torch(res).view(-1, 3)
    elif kind == "warp":
        r = res
    else:
        r = res.numpy()
    return r[0] if single else r


# ---- compilation --------------------------------------------------------------------------------------------------------

def warmup(model: Model, device=None, precision: str = "auto") -> dict:
    """Compile (or load from Warp's kernel cache) every kernel the queries use on ``device``, by answering one
    tiny query of each kind; nothing is kept (no vertex embeddings).

    Returns {"seconds": wall time}. Later calls in the process find the kernels loaded; a new process loads them
    from Warp's kernel cache (``wp.config.kernel_cache_dir``) in milliseconds instead of compiling.
    """
    dev = resolve_device(device)
    prec = _precision(model, precision, dev)
    t0 = time.perf_counter()
    x = model.mesh.vertices[:2] if model.mesh is not None else np.array([[0.1, 0.2, 0.3], [-0.3, 0.1, 0.0]])
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
