"""The state a model keeps per device for its queries: folded weights, the user -> network frame, the tensor-core
engine, the mesh's vertices and component labels, and the vertex embeddings kept by ``bind``.

Everything lives in ``model._warp`` under keys that name the device, so a model serves several devices at once
and ``Model.unbind`` frees what a binding kept.
"""
from __future__ import annotations

import numpy as np
import warp as wp

from neurogf_warp.common.arrays import resolve_device
from neurogf_warp.inference.engine import Engine, supported
from neurogf_warp.kernels.inference import finish, mlp
from neurogf_warp.model.folded import fold_batchnorm
from neurogf_warp.model.model import Model

PRECISIONS = ("auto", "fp16", "fp32")


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


def frame_of(model: Model) -> mlp.Frame:
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


def engine_of(model: Model, dev) -> Engine:
    key = ("engine", str(dev))
    if key not in model._warp:
        model._warp[key] = Engine(model.net, frame_of(model), dev)
    return model._warp[key]


def precision_of(model: Model, precision: str, dev) -> str:
    if precision not in PRECISIONS:
        raise ValueError(f"precision must be one of {PRECISIONS}, got {precision!r}")
    if precision == "auto":
        return "fp16" if dev.is_cuda and supported(model.net) else "fp32"
    if precision == "fp16" and not supported(model.net):
        raise ValueError(f"precision='fp16' supports D in (64, 128, 256), this network has D={model.D}: "
                         "use precision='fp32'")
    return precision


class MeshOnDevice:
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


def mesh_on(model: Model, dev, what: str) -> MeshOnDevice:
    if model.mesh is None:
        raise ValueError(f"{what} needs the model's mesh: load the model with neurogf_warp.load(path, mesh=...)")
    key = ("mesh", str(dev))
    if key not in model._warp:
        model._warp[key] = MeshOnDevice(model, dev)
    md = model._warp[key]
    if md.multi and md._wp_mesh is None:
        m = model.mesh
        md._wp_mesh = wp.Mesh(points=md.verts, indices=wp.array(m.faces.reshape(-1).astype(np.int32), device=dev))
        md._face_comp = wp.array(m.components[m.faces[:, 0]].astype(np.int32), dtype=wp.int32, device=dev)
    return md


def binding_of(model: Model, dev, precision: str):
    return model._warp.get(("bound", str(dev), precision))


def bind(model: Model, device=None, precision: str = "auto") -> int:
    """Embed every mesh vertex once and keep the result on ``device`` for later vertex queries; returns bytes kept.

    fp16: packed (V, D/2) uint32, 2 D bytes per vertex; fp32: (V, D) float32, 4 D bytes per vertex.
    """
    dev = resolve_device(device)
    prec = precision_of(model, precision, dev)
    md = mesh_on(model, dev, "binding")
    b = binding_of(model, dev, prec)
    if b is None:
        need = md.V * model.D * (2 if prec == "fp16" else 4)
        check_memory(dev, need, f"keeping the embeddings of {md.V:,} vertices ({need / 1e6:.0f} MB)",
                      "query with cache=False (every call then embeds the vertices) or free GPU memory", 0.5)
        if prec == "fp16":
            b = engine_of(model, dev).embed(md.verts)
        else:
            b = embed_fp32(model, md.verts, dev)
        model._warp[("bound", str(dev), prec)] = b
    return int(b.capacity)


def check_memory(dev, need: int, what: str, hint: str, share: float = 0.9):
    """MemoryError, with the sizes and what to do, when ``need`` bytes exceed ``share`` of the device's free memory."""
    if not dev.is_cuda:
        return
    free = getattr(dev, "free_memory", None)
    if free and need > share * free:
        raise MemoryError(f"{what} needs {need / 1e9:.2f} GB, but {free / 1e9:.2f} GB is free on {dev}: {hint}")


def unbind(model: Model, device=None) -> None:
    """Free the vertex embeddings kept on ``device`` (all devices when None)."""
    for key in [k for k in model._warp if k[0] == "bound" and (device is None or k[1] == str(resolve_device(device)))]:
        del model._warp[key]


def embed_fp32(model: Model, pts: wp.array, dev) -> wp.array:
    """Embeddings e(x) of (N,) vec3 points by the float32 per-thread kernel: (N, D) float32."""
    out = wp.empty((pts.shape[0], model.D), dtype=wp.float32, device=dev)
    if pts.shape[0]:
        wp.launch(mlp.embed_points, pts.shape[0], inputs=[warp_weights(model, dev), pts, frame_of(model)],
                  outputs=[out], device=dev)
    return out


def bound_tables(model: Model, dev, md, bound):
    """(rows, sources) tables of a bound model's vertices for the tensor-core kernels (made once per binding)."""
    key = ("bound_tables", str(dev))
    t = model._warp.get(key)
    if t is None or t[0] is not bound:
        eng = engine_of(model, dev)
        t = (bound, eng.rows(md.verts, bound, md.comp), eng.sources(bound, md.verts, md.comp))
        model._warp[key] = t
    return t[1], t[2]


def head_only_weights(model: Model, dev) -> mlp.NeuroGFWeights:
    """The folded weights with the |x - s| term switched off: raw head values for kernels.finish."""
    key = ("head_weights", str(dev))
    if key not in model._warp:
        w, h = warp_weights(model, dev), mlp.NeuroGFWeights()
        for name in mlp.NeuroGFWeights.vars:
            setattr(h, name, getattr(w, name))
        h.euclid = 0.0
        model._warp[key] = h
    return model._warp[key]
