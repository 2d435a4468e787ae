"""What a model keeps on one device for its queries: ``QueryState``, one per (model, device).

A state owns the model's folded float32 weights, the user -> network frame, the mesh's tables (vertices,
component labels, numbering map), the vertex embeddings kept by ``bind`` and the tables and recorded launches
made from them, the tensor-core engine and its tuning, and the small buffers of the input checks. Everything is
made on first use. ``unbind`` frees the kept embeddings and everything that refers to them; ``close`` frees the
whole state. The model holds its states in ``model._states`` (device name -> state) and knows them only through
the two methods ``unbind()`` and ``close()`` (``Model.unbind`` / ``Model.invalidate``), so the model stage does
not import this one.
"""
from __future__ import annotations

import numpy as np
import warp as wp

from neurogf_warp.common.arrays import resolve_device
from neurogf_warp.common.checks import InputError
from neurogf_warp.inference.engine import Engine
from neurogf_warp.inference.launches import Recorded
from neurogf_warp.kernels.inference import finish, landmark, mlp
from neurogf_warp.kernels.inference import tensorcore as tc
from neurogf_warp.model.folded import folded_layers, net_shape
from neurogf_warp.model.model import Model

__all__ = ["PRECISIONS", "DOMAIN", "QueryState", "MeshOnDevice", "query_state", "to_relative", "unbind", "check_memory",
           "landmark_rows"]

PRECISIONS = ("auto", "fp16", "fp32")
_KEPT_ID_SETS, _KEPT_ID_LEN = 8, 4096  # vertex-index sets kept on the device per state, and their largest size
DOMAIN = 1.5  # half-side of the domain cube, normalized frame (the networks were trained within [-1.01, 1.01]^3)


class MeshOnDevice:
    """The mesh's internal vertices relative to its centre (``x - center`` in float64, then float32: the
    ``QueryState.frame`` coordinates), component labels and numbering map on one device."""

    def __init__(self, model: Model, dev):
        m = model.mesh
        self.V, self.n_input = len(m.internal_vertices), m.n_input
        rel = np.asarray(m.internal_vertices, np.float64) - model.center
        self.verts = wp.array(rel.astype(np.float32), dtype=wp.vec3, device=dev)
        self.multi = m.n_components > 1
        self.comp = wp.array(m.internal_components.astype(np.int32), dtype=wp.int32, device=dev) if self.multi else None
        inv = m.input_to_internal
        self.identity = self.n_input == self.V and bool(np.array_equal(inv, np.arange(self.V)))
        self.inv = None if self.identity else wp.array(inv.astype(np.int32), dtype=wp.int32, device=dev)
        self.dev = dev
        self.rel64 = rel  # (V, 3) float64 relative vertices: vertex sources without arithmetic per query
        self.lifted = None  # fp16 rows of the vertices embedded inside the kernels (no kept embeddings)
        self._wp_mesh = self._face_comp = self._landmarks = None
        # closest-point queries give a point's component and a landmark network's table row (relative coordinates)
        if self.multi or model.net.landmarks:
            self._wp_mesh = wp.Mesh(points=self.verts, indices=wp.array(m.internal_faces.reshape(-1).astype(np.int32),
                                                                         device=dev))
        if self.multi:
            self._face_comp = wp.array(m.internal_components[m.internal_faces[:, 0]].astype(np.int32), dtype=wp.int32,
                                       device=dev)

    def landmark_table(self, model: Model) -> landmark.LandmarkTable:
        """A landmark network's table (``landmark_rows``, internal order) on the device with the mesh it lives on, in
        these relative coordinates (made on first use; the model's landmark options are read then)."""
        if self._landmarks is None:
            rows = wp.array(landmark_rows(model), dtype=wp.float32, device=self.dev)
            self._landmarks = landmark_struct(model, rows, self.verts, self._wp_mesh)
        return self._landmarks

    def components_of(self, pts: wp.array) -> wp.array:
        """Component label of each point, relative coordinates (that of its closest surface point; -1 for a
        non-finite point)."""
        out = wp.empty(pts.shape[0], dtype=wp.int32, device=self.dev)
        if pts.shape[0]:
            wp.launch(finish.point_components, pts.shape[0], inputs=[self._wp_mesh.id, pts, self._face_comp],
                      outputs=[out], device=self.dev)
        return out


class QueryState:
    """Everything one model keeps on one device for its queries (see the module docstring).

    Coordinates: ``frame`` takes points relative to the mesh centre (``x - center``, made in float64 on the
    host: the mesh's vertices, sources and host query points); ``user_frame`` takes points in mesh coordinates
    (float32 arrays already on a device), subtracting the float64 centre in the kernels. Without a mesh both are
    the identity. Both are ``mlp.Frame``s with the domain limit.

    Attributes made on first use: ``weights`` (``mlp.NeuroGFWeights``, folded float32), ``head_weights`` (the
    same with the |x - s| term off), ``shape`` (``folded.NetShape``), ``engine`` (``engine.Engine``, fp16 only),
    ``mesh(what)`` (``MeshOnDevice``), ``backends``, ``bound`` ({precision: kept embeddings}), ``tables`` (the
    fp16 rows and sources made from the fp16 binding), ``launches`` (the queries' recorded finishing launches).
    """

    def __init__(self, model: Model, dev, tuning: tc.Tuning = tc.Tuning()):
        self.model, self.device, self.tuning = model, dev, tuning
        self.layers = folded_layers(model.net)  # float64, BatchNorm folded
        self.shape = net_shape(self.layers)
        self.options = dict(model.net.options)
        self.center = np.asarray(model.center, np.float64) if model.in_mesh_frame else np.zeros(3)
        scale = float(model.scale) if model.in_mesh_frame else 1.0
        with np.errstate(over="ignore"):
            s32, d32 = np.float32(scale), np.float32(1.0 / scale)
        if not (np.isfinite(s32) and np.isfinite(d32) and s32 > 0 and d32 > 0 and np.all(np.isfinite(self.center))):
            raise InputError(f"the mesh's size ({1.0 / scale:.3g} units per bounding radius) is beyond float32, "
                             "the kernels' number type: rescale the mesh (and its units) into float32's range")
        self.frame = _make_frame(np.zeros(3), scale)
        self.user_frame = _make_frame(self.center, scale)
        self._weights = self._head_weights = self._engine = self._mesh = self._multi = None
        self._kernel_landmarks = None  # (wp.Mesh, LandmarkTable) in the network frame, for users' kernels
        self.backends = {}  # precision asked for -> backend (backends.backend_of)
        self.bound = {}
        self.tables = None
        self.tile_head = None  # the fp32 head's weights as the tile kernel takes them
        self.check_buffers = (wp.empty(2, dtype=wp.int32, device=dev),
                              wp.empty(2, dtype=wp.int32, device="cpu", pinned=dev.is_cuda))
        self.no_points = wp.empty(0, dtype=wp.vec3, device=dev)
        self.no_ints = wp.empty(0, dtype=wp.int32, device=dev)
        self.launches = Recorded(dev)  # the public queries' own recorded launches (finishing passes)
        self.point_source = None  # fp16 buffers of one source point (backends.TensorCores._point_source)
        self._ids = {}  # vertex-index arrays of recent many-source queries on the device (ids_on_device)

    # -- parts made on first use ----------------------------------------------------------------------------
    @property
    def weights(self) -> mlp.NeuroGFWeights:
        """The folded float32 weights for the per-thread ``@wp.func``s."""
        if self._weights is None:
            w = mlp.NeuroGFWeights()
            groups = {"l": self.layers["lifting"], "g": self.layers["distance"], "s": self.layers["sdf"],
                      "c": [self.layers["guidance"]], "p": self.layers["path"]}
            for prefix, stack in groups.items():
                for i, (W, b) in enumerate(stack):
                    name = f"{prefix}{i}" if prefix != "c" else "c"
                    setattr(w, f"{name}_w", wp.array(W.astype(np.float32), dtype=wp.float32, device=self.device))
                    if b is not None:
                        setattr(w, f"{name}_b", wp.array(b.astype(np.float32), dtype=wp.float32, device=self.device))
            w.euclid = 1.0 if self.options["euclid"] else 0.0
            w.residual = 1.0 if self.options["path_residual"] else 0.0
            w.window = 1.0 if self.options["path_window"] else 0.0
            self._weights = w
        return self._weights

    @property
    def head_weights(self) -> mlp.NeuroGFWeights:
        """The folded weights with the |x - s| term switched off: raw head values for ``kernels.finish``."""
        if self._head_weights is None:
            w, h = self.weights, mlp.NeuroGFWeights()
            for name in mlp.NeuroGFWeights.vars:
                setattr(h, name, getattr(w, name))
            h.euclid = 0.0
            self._head_weights = h
        return self._head_weights

    @property
    def engine(self):
        """The tensor-core engine (packed fp16 weights, recorded launches); refuses networks it cannot run."""
        if self._engine is None:
            self._engine = Engine(self.layers, self.shape, self.options, self.frame, self.device, self.tuning)
        return self._engine

    @property
    def multi(self) -> bool:
        """Whether the model's mesh has several connected components (read once: the count is a pass over every
        vertex label, too slow for each query)."""
        if self._multi is None:
            self._multi = self.model.mesh is not None and self.model.mesh.n_components > 1
        return self._multi

    def mesh(self, what: str) -> MeshOnDevice:
        """The mesh's tables on this device; ``what`` names the query for the error without a mesh."""
        if self._mesh is None:
            if self.model.mesh is None:
                raise ValueError(f"{what} needs the model's mesh: load the model with neurogf_warp.load(path, "
                                 "mesh=...)")
            self._mesh = MeshOnDevice(self.model, self.device)
        return self._mesh

    def kernel_landmarks(self) -> landmark.LandmarkTable:
        """A landmark network's table for users' kernels (``kernels.field``): the mesh's vertices and a ``wp.Mesh`` of
        them in the network frame, sharing the device rows of ``MeshOnDevice.landmark_table`` (made on first use)."""
        if self._kernel_landmarks is None:
            md = self.mesh("a landmark network's table")
            rows = md.landmark_table(self.model).rows
            # the network frame as to_net maps a vertex: (x - centre) in float64, times the float32 scale
            pts = wp.array((md.rel64 * float(self.frame.xscale)).astype(np.float32), dtype=wp.vec3, device=self.device)
            mesh = wp.Mesh(points=pts, indices=md.landmark_table(self.model).indices)
            self._kernel_landmarks = (mesh, landmark_struct(self.model, rows, pts, mesh))
        return self._kernel_landmarks[1]

    def retune(self, tuning: tc.Tuning):
        """Use other tile settings from now on (a new engine; the kept embeddings stay)."""
        self.tuning = tuning
        self._engine = None
        self.tables = None
        self.point_source = None
        if self._mesh is not None:
            self._mesh.lifted = None
        self.backends.clear()

    def ids_on_device(self, ids: np.ndarray) -> wp.array:
        """Internal vertex indices (S,) as an int32 array on the device, kept for the last few index sets: a
        repeated query (the same sources) makes no copy from the host, which would wait for the stream's work."""
        if len(ids) > _KEPT_ID_LEN:
            return wp.array(ids.astype(np.int32), dtype=wp.int32, device=self.device)
        key = ids.astype(np.int64, copy=False).tobytes()
        arr = self._ids.pop(key, None)
        if arr is None:
            arr = wp.array(ids.astype(np.int32), dtype=wp.int32, device=self.device)
            while len(self._ids) >= _KEPT_ID_SETS:
                del self._ids[next(iter(self._ids))]  # the oldest first (dicts keep insertion order)
        self._ids[key] = arr  # most recent last
        return arr

    # -- freeing -----------------------------------------------------------------------------------------------
    def unbind(self):
        """Free the kept vertex embeddings and everything made from them (tables, recorded launches)."""
        self.bound.clear()
        self.tables = None
        self.launches.clear()
        self._ids.clear()
        if self._engine is not None:
            self._engine.forget_launches()

    def close(self):
        """Free everything this state holds on its device."""
        self.unbind()
        self._weights = self._head_weights = self._engine = self._mesh = self.tile_head = None
        self.point_source = self._kernel_landmarks = None
        self.backends.clear()


def landmark_rows(model: Model) -> np.ndarray:
    """(V, K) float32: a landmark network's table (``model.landmarks``, file numbering) in the mesh's internal
    vertex order (input vertices merged into one internal vertex share their distances)."""
    if not model.net.landmarks:
        raise ValueError("this network has no landmark table (landmarks=0)")
    if model.mesh is None or model.landmarks is None:
        raise ValueError("a landmark network answers from its table of distances at the mesh's vertices: load the "
                         "model with its mesh (neurogf_warp.load(path, mesh=...)) from a file that stores the table")
    return model.internal_landmarks()


def landmark_struct(model: Model, rows: wp.array, points: wp.array, mesh: wp.Mesh) -> landmark.LandmarkTable:
    """A ``landmark.LandmarkTable`` of ``rows`` ((V, K) float32 on the device) on the vertices ``points`` (vec3, in the frame
    its users pass points in) and ``mesh`` (a wp.Mesh of them, which must outlive the struct), with the network's
    options."""
    net = model.net
    t = landmark.LandmarkTable()
    t.rows = rows
    t.indices = mesh.indices
    t.points = points
    t.mesh = mesh.id
    t.floor = float(net.landmark_floor)
    t.bracket = int(net.landmark_bracket)
    t.euclid = 1.0 if net.euclid else 0.0
    return t


def _make_frame(center: np.ndarray, scale: float) -> mlp.Frame:
    return mlp.make_frame(center, scale, limit=DOMAIN)


def to_relative(state: "QueryState", x: np.ndarray) -> np.ndarray:
    """Host points in mesh coordinates -> relative to the mesh centre, in float64 (``state.frame`` coordinates)."""
    return np.asarray(x, np.float64) - state.center


def query_state(model: Model, device=None) -> QueryState:
    """The model's ``QueryState`` on ``device`` (made on first use; Warp's preferred device when None)."""
    if isinstance(device, wp.Device):  # the queries' own calls: no device resolution on the hot path
        st = model._states.get(str(device))
        if st is not None:
            return st
    elif type(device) is str and device != "cuda":  # "cpu", "cuda:N" name one device whatever the current one
        st = model._states.get(device)
        if st is not None:
            return st
    dev = resolve_device(device)
    key = str(dev)
    st = model._states.get(key)
    if st is None:
        st = model._states[key] = QueryState(model, dev)
    return st


def check_memory(dev, need: int, what: str, hint: str, share: float = 0.9):
    """MemoryError, with the sizes and what to do, when ``need`` bytes exceed ``share`` of the device's free memory."""
    if not dev.is_cuda:
        return
    free = getattr(dev, "free_memory", None)
    if free and need > share * free:
        raise MemoryError(f"{what} needs {need / 1e9:.2f} GB, but {free / 1e9:.2f} GB is free on {dev}: {hint}")


def unbind(model: Model, device=None) -> None:
    """Free the vertex embeddings kept on ``device`` (all devices when None) and everything made from them."""
    model.unbind(None if device is None else resolve_device(device))
