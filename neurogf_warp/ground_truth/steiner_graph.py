"""The ground-truth solver's mesh tables: unique edges, face/edge incidence, and which faces windows may cross.

Built once per solver on the host (numpy), then uploaded as one `SteinerGraph` struct (kernels/ground_truth/graph.py),
whose largest tables (per Steiner node and per face slot) are written on the device (kernels/ground_truth/build.py);
the numpy functions here that give the same tables are their reference.
"""
from __future__ import annotations

import numpy as np

__all__ = ["Topology", "window_faces", "face_geometry", "steiner_counts", "face_slot_table", "face_slot_start",
           "node_positions", "steiner_node_tables", "stable_sort", "STEINER_ASPECT", "MAX_STEINER"]

WINDOW_FACE_MIN_RELATIVE_HEIGHT = 1e-6  # smallest height / longest edge of a face windows may cross
WINDOW_FACE_MIN_HEIGHT = 1e-7  # and smallest height in the normalized frame (float32 positions)
STEINER_ASPECT = 2.0  # an edge longer than this many times its faces' smallest height gets more Steiner points
MAX_STEINER = 64  # the most Steiner points on one edge (32 left a 0.97% pair on an icosphere scaled (1, 0.01, 0.01))
GRAPH_ONLY_FACTOR = 2  # edges of graph-only faces get 2k points (needles, 24 sources: max 1.263% -> 0.640%)


class Topology:
    """Unique edges, face->edge and edge->face tables (numpy), with degenerate faces removed.

    Attributes: faces (F, 3) int32 (faces that repeat a vertex dropped); edges (E, 2) int32, lower vertex first;
    face_edges (F, 3) int32, the edge of local edge le (vertices le, (le + 1) % 3); vertex_face_start /
    vertex_faces and edge_face_start / edge_faces: CSR lists of the faces around each vertex and of every face of
    each edge (in face order); nonmanifold_edges, boundary_edges: counts of edges with three or more faces and
    with one; face_ok (F,) int8: window faces (`window_faces`).
    """

    def __init__(self, vertices: np.ndarray, faces: np.ndarray):
        f = np.asarray(faces, dtype=np.int64)
        # faces repeating a vertex carry no area and would create zero-length edges
        keep = (f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 2] != f[:, 0])
        if not keep.all():
            f = f[keep]
        nvtx = len(vertices)
        # unique edges from one stable sort of int64 keys (lower * V + higher); the sort also gives each edge's
        # faces in face order, so no second sort is needed (np.unique(axis=0) plus two argsorts took 65 s for a
        # 2.2M-vertex mesh on a 2-core machine)
        a = f.reshape(-1)
        b = f[:, [1, 2, 0]].reshape(-1)
        key = np.minimum(a, b)
        key *= max(nvtx, 1)
        key += np.maximum(a, b)
        sk, order = stable_sort(key, max(nvtx, 1) ** 2)
        new = np.ones(len(sk), dtype=bool)
        new[1:] = sk[1:] != sk[:-1]
        ids = np.cumsum(new) - 1
        inv = np.empty(len(key), dtype=np.int64)
        inv[order] = ids
        uk = sk[new]
        edges = np.stack([uk // max(nvtx, 1), uk % max(nvtx, 1)], axis=1)
        self.faces = f.astype(np.int32)
        self.edges = edges.astype(np.int32)
        self.face_edges = inv.reshape(-1, 3).astype(np.int32)
        ne = len(edges)
        counts = np.bincount(ids, minlength=ne) if len(ids) else np.zeros(0, np.int64)
        self.nonmanifold_edges = int(np.sum(counts > 2))  # edges with three or more faces
        self.boundary_edges = int(np.sum(counts == 1))
        self.edge_faces = (order // 3).astype(np.int32)
        self.edge_face_start = np.r_[0, np.cumsum(counts)].astype(np.int32)
        # faces around each vertex, in face order (a stable sort; scipy's CSR build would save it, but importing
        # scipy.sparse costs the solver's worker processes 0.4 s of start-up)
        _, fo = stable_sort(a, max(nvtx, 1))
        self.vertex_faces = (fo // 3).astype(np.int32)
        self.vertex_face_start = np.r_[0, np.cumsum(np.bincount(a, minlength=nvtx))].astype(np.int32)
        self._vertices = np.asarray(vertices, dtype=np.float64)
        self._geometry = face_geometry(self._vertices, f)
        self.face_ok = window_faces(self._vertices, f, self._geometry)

    def steiner_start(self, k: int, adaptive: bool = True) -> np.ndarray:
        """(E + 1,) int32: offsets from V of each edge's Steiner nodes, `steiner_counts` points per edge (k each
        when not adaptive)."""
        c = steiner_counts(self._vertices, self.faces, self.face_edges, len(self.edges), k, self.face_ok,
                           self._geometry) if adaptive else np.full(len(self.edges), k, np.int64)
        return np.r_[0, np.cumsum(c)].astype(np.int32)

    def steiner_nodes(self, k: int, adaptive: bool = True, start: np.ndarray | None = None):
        """The Steiner points: (edge_node_start (E + 1,) int32 offsets from V, node_edge (N - V,) int32, node_t
        (N - V,) float32 parameter from the edge's lower vertex), `steiner_counts` points per edge (k each when
        not adaptive), evenly spaced. start: `steiner_start(k, adaptive)` if already computed."""
        if start is None:
            start = self.steiner_start(k, adaptive)
        return (np.asarray(start, dtype=np.int32),) + steiner_node_tables(start)

    def to_warp(self, positions: np.ndarray, k: int, windows: bool, device, nodes=None, timings: dict | None = None):
        """The `SteinerGraph` struct of these tables on `device`; positions (V, 3) float32, normalized frame;
        nodes: `steiner_start(k)` (computed when not given; a `steiner_nodes` tuple is taken too, its first
        entry used). The per-node and per-slot tables are written on the device (kernels/ground_truth/build.py),
        equal bit for bit to `steiner_node_tables`, `node_positions` and `face_slot_table`. timings: a dict that
        gets each phase's seconds added."""
        import time

        import warp as wp

        from neurogf_warp.kernels.ground_truth import build
        from neurogf_warp.kernels.ground_truth.graph import SteinerGraph

        t = timings if timings is not None else {}
        t0 = time.perf_counter()

        def lap(name):
            nonlocal t0
            now = time.perf_counter()
            t[name] = t.get(name, 0.0) + now - t0
            t0 = now

        if nodes is None:
            nodes = self.steiner_start(k)
        start = np.asarray(nodes[0] if isinstance(nodes, tuple) else nodes, dtype=np.int32)
        counts = np.diff(start)
        nv, ns = len(positions), int(start[-1]) if len(start) else 0
        slot_start = face_slot_start(self.face_edges, start, nv)
        lap("slot_start")
        up = lambda x, dt: wp.array(x, dtype=dt, device=device)  # noqa: E731
        g = SteinerGraph()
        g.nv = nv
        g.k = int(k)
        g.kmax = int(counts.max()) if len(counts) else int(k)
        g.windows = int(bool(windows))
        g.edge_node_start = up(start, int)
        g.pos = up(np.asarray(positions, dtype=np.float32), wp.vec3)
        g.faces = up(self.faces, int)
        g.edges = up(self.edges, int)
        g.face_edges = up(self.face_edges, int)
        g.window_face = up(self.face_ok, wp.int8)
        g.vertex_face_start = up(self.vertex_face_start, int)
        g.vertex_faces = up(self.vertex_faces, int)
        g.edge_face_start = up(self.edge_face_start, int)
        g.edge_face_list = up(self.edge_faces, int)
        g.face_slot_start = up(slot_start, int)
        lap("upload")
        # every entry is written by the kernels below (a table of no Steiner nodes keeps one unused zero)
        alloc = wp.empty if ns else wp.zeros
        g.node_edge = alloc(max(ns, 1), dtype=int, device=device)
        g.node_t = alloc(max(ns, 1), dtype=float, device=device)
        g.node_xyz = wp.empty(nv + ns, dtype=wp.vec3, device=device)
        g.face_slot = wp.empty(int(slot_start[-1]), dtype=int, device=device)
        if nv:
            wp.launch(build.copy_vertices, dim=nv, inputs=[g.pos, g.node_xyz], device=device)
        if len(self.edges):
            wp.launch(build.steiner_nodes, dim=len(self.edges), device=device,
                      inputs=[g.edges, g.edge_node_start, g.pos, nv, g.node_edge, g.node_t, g.node_xyz])
        if len(self.faces):
            wp.launch(build.face_slots, dim=len(self.faces), device=device,
                      inputs=[g.faces, g.face_edges, g.edge_node_start, g.face_slot_start, nv, g.face_slot])
        lap("device_tables")
        return g


SLOT_EDGE_BITS = 3  # face_slot_table: the low bits of a slot code, one per local edge the slot lies on


def stable_sort(keys: np.ndarray, bound: int):
    """(sorted keys, order): ``order = np.argsort(keys, kind="stable")`` and ``keys[order]``, for int64 keys in
    [0, bound). Where bound * len(keys) fits in int64 it sorts the values key * n + position instead, which are
    distinct (so any sort is stable) and sort about 3x faster than the indirect sort; the result is the same."""
    keys = np.asarray(keys, dtype=np.int64)
    n = len(keys)
    if n == 0 or int(bound) * n >= 2**63:
        order = np.argsort(keys, kind="stable")
        return keys[order], order
    c = keys * n
    c += np.arange(n, dtype=np.int64)
    c.sort()
    sk, order = np.divmod(c, n)
    return sk, order


def steiner_node_tables(edge_node_start: np.ndarray):
    """(node_edge (S,) int32, node_t (S,) float32) of the Steiner nodes that ``edge_node_start`` (E + 1,) lays
    out: each node's edge and its parameter t = (j + 1) / (count + 1) from the edge's lower vertex (j: its rank
    on the edge)."""
    start = np.asarray(edge_node_start, dtype=np.int64)
    c = np.diff(start)
    node_edge = np.repeat(np.arange(len(c)), c)
    j = np.arange(start[-1] if len(start) else 0) - start[node_edge]
    node_t = (j + 1.0) / (c[node_edge] + 1.0)
    return node_edge.astype(np.int32), node_t.astype(np.float32)


def face_slot_start(face_edges: np.ndarray, edge_node_start: np.ndarray, nv: int) -> np.ndarray:
    """(F + 1,) int32: offsets of each face's slots in ``face_slot_table``'s codes (3 + its edges' Steiner
    points per face). ValueError where the graph's node ids do not fit the slot codes."""
    start = np.asarray(edge_node_start, dtype=np.int64)
    n_nodes = nv + int(start[-1]) if len(start) else nv
    if n_nodes >= 1 << (31 - SLOT_EDGE_BITS):
        raise ValueError(f"mesh too large for the solver's face slot codes ({n_nodes:,} graph nodes, at most "
                         f"{(1 << (31 - SLOT_EDGE_BITS)) - 1:,}); lower k or decimate the mesh")
    counts = np.diff(start)
    per_face = counts[np.asarray(face_edges, dtype=np.int64)].sum(axis=1) + 3
    out = np.zeros(len(per_face) + 1, dtype=np.int64)
    np.cumsum(per_face, out=out[1:])
    if out[-1] >= 2**31:
        raise ValueError(f"mesh too large for the solver's face slot table ({int(out[-1]):,} slots, at most "
                         f"{2**31 - 1:,}); lower k or decimate the mesh")
    return out.astype(np.int32)


def face_slot_table(faces: np.ndarray, face_edges: np.ndarray, edge_node_start: np.ndarray, nv: int):
    """Every face's slots (graph.py: its 3 vertices, then the Steiner points of its local edges 0, 1, 2 in turn) as
    one CSR table: (slot_start (F + 1,) int32, slots (F, ...) int32), each slot coded node << 3 | edges, where bit le
    of edges is set when the slot lies on local edge le (a vertex slot i on i and (i + 2) % 3). The relax loop reads
    one code per candidate where walking the face's edge tables took a chain of dependent loads."""
    f = np.asarray(faces, dtype=np.int64)
    fe = np.asarray(face_edges, dtype=np.int64)
    start = np.asarray(edge_node_start, dtype=np.int64)
    n_nodes = nv + int(start[-1]) if len(start) else nv
    if n_nodes >= 1 << (31 - SLOT_EDGE_BITS):
        raise ValueError(f"mesh too large for the solver's face slot codes ({n_nodes:,} graph nodes, at most "
                         f"{(1 << (31 - SLOT_EDGE_BITS)) - 1:,}); lower k or decimate the mesh")
    F = len(f)
    c = start[fe + 1] - start[fe]  # (F, 3) Steiner points per local edge
    per_face = 3 + c.sum(axis=1)
    slot_start = np.r_[0, np.cumsum(per_face)]
    codes = np.empty(int(slot_start[-1]), dtype=np.int64)
    first = slot_start[:-1]
    for i in range(3):  # vertex slots
        codes[first + i] = (f[:, i] << SLOT_EDGE_BITS) | (1 << i) | (1 << ((i + 2) % 3))
    # Steiner slots, local edge by local edge: a ragged arange per (face, le)
    off = first + 3
    for le in range(3):
        n = c[:, le]
        rows = np.repeat(np.arange(F), n)
        r = np.arange(int(n.sum())) - np.repeat(np.cumsum(n) - n, n)
        node = nv + start[fe[rows, le]] + r
        codes[off[rows] + r] = (node << SLOT_EDGE_BITS) | (1 << le)
        off = off + n
    return slot_start.astype(np.int32), codes.astype(np.int32)


def node_positions(positions: np.ndarray, edges: np.ndarray, node_edge: np.ndarray, node_t: np.ndarray) -> np.ndarray:
    """(V + S, 3) float32: the vertices, then each Steiner point at a + t (b - a) on its edge (a: the edge's lower
    vertex), each operation rounded to float32 as the kernels once computed it per use (no fused multiply-add:
    the solver's modules are built with fuse_fp off), so the table gives the same bits."""
    p = np.asarray(positions, dtype=np.float32)
    e = np.asarray(edges, dtype=np.int64)[np.asarray(node_edge, dtype=np.int64)]
    a, b = p[e[:, 0]], p[e[:, 1]]
    t = np.asarray(node_t, dtype=np.float32)[:, None]
    return np.concatenate([p, a + t * (b - a)]).astype(np.float32)


def _rowmax3(a: np.ndarray) -> np.ndarray:
    """a.max(axis=1) of an (n, 3) array (NaN propagating as there), elementwise: several times faster than the
    reduction over a short axis."""
    return np.maximum(np.maximum(a[:, 0], a[:, 1]), a[:, 2])


def face_geometry(vertices: np.ndarray, faces: np.ndarray):
    """(area2 (F,), elen (F, 3)) float64: twice each face's area and the length of its local edges (local edge le
    joins vertices le and (le + 1) % 3), in the units of `vertices`."""
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    e0, e1, e2 = b - a, c - b, a - c
    elen = np.sqrt(np.stack([np.einsum("ij,ij->i", e, e) for e in (e0, e1, e2)], axis=1))
    # cross(e0, -e2) by components (np.cross is several times slower on millions of rows)
    cx = e0[:, 2] * e2[:, 1] - e0[:, 1] * e2[:, 2]
    cy = e0[:, 0] * e2[:, 2] - e0[:, 2] * e2[:, 0]
    cz = e0[:, 1] * e2[:, 0] - e0[:, 0] * e2[:, 1]
    return np.sqrt(cx * cx + cy * cy + cz * cz), elen


def window_faces(vertices: np.ndarray, faces: np.ndarray, geometry=None) -> np.ndarray:
    """(F,) int8: 1 where unfolding windows may cross the face, 0 for graph-only faces.

    Unfolding a virtual source across an edge needs the in-plane direction towards the face's third vertex. The
    kernels compute it in float64 from the float32 positions, which define it exactly for any face whose third
    vertex is off the edge's line by more than the positions' rounding; thin faces (needles from split edges,
    slivers) are crossed like any other. Faces at the rounding level (zero area, coincident or collinear vertices)
    keep only their graph edges (always real segments): there the direction is noise, and the unfolded source
    would land anywhere. A face is kept for windows when its smallest height (2 area / longest edge) is at least
    1e-6 of its longest edge and 1e-7 absolute (pass the float32 positions the kernels use, in the normalized
    unit-sphere frame, where 1e-7 is about two float32 steps). geometry: `face_geometry` if already computed."""
    f = np.asarray(faces, dtype=np.int64)
    if len(f) == 0:
        return np.zeros(0, np.int8)
    area2, elen = geometry if geometry is not None else face_geometry(vertices, f)
    lmax = _rowmax3(elen)
    hmin = area2 / np.maximum(lmax, 1e-300)
    ok = (hmin >= WINDOW_FACE_MIN_RELATIVE_HEIGHT * lmax) & (hmin >= WINDOW_FACE_MIN_HEIGHT) & np.isfinite(hmin)
    return ok.astype(np.int8)


def steiner_counts(vertices: np.ndarray, faces: np.ndarray, face_edges: np.ndarray, n_edges: int, k: int,
                   face_ok: np.ndarray | None = None, geometry=None) -> np.ndarray:
    """(E,) int64: Steiner points per edge, k on well-shaped faces and more on an edge much longer than the faces
    beside it are wide.

    Why: each node keeps one unfolding window, chosen by the node's own distance. Where faces are long and thin
    (stretched meshes, fans, needles) geodesics cross the long edges at distances from the nodes much larger than
    the paths' own length scale (the faces' width), the node nearest a crossing is best reached by another route,
    and the ray's window is lost (an icosphere scaled (1, 0.01, 0.01): 36% too long at k=3 everywhere). Spacing
    the nodes in proportion to the width keeps the beams. Each face asks round(k L / (STEINER_ASPECT h)) points
    of each of its edges (L: the edge's length, h: the face's smallest height, 2 area / longest edge), at least k
    and at most MAX_STEINER, and an edge gets what its widest face asks (the fewest): the long edges of a needle
    beside a fat face keep k, a mesh where every face is thin is refined. Faces where windows do not go (face_ok
    0: zero area) ask k. geometry: `face_geometry` if already computed.
    """
    f = np.asarray(faces, dtype=np.int64)
    counts = np.full(n_edges, int(k), dtype=np.int64)
    if len(f) == 0:
        return counts
    area2, elen = geometry if geometry is not None else face_geometry(vertices, f)
    h = area2 / np.maximum(_rowmax3(elen), 1e-300)
    ok = np.ones(len(f), bool) if face_ok is None else np.asarray(face_ok) != 0
    ok &= h > 0
    # per (face, local edge): the points that face asks of the edge
    want = np.where(ok[:, None], np.rint(k * elen / (STEINER_ASPECT * np.maximum(h, 1e-300))[:, None]), k)
    want = np.clip(want, k, MAX_STEINER).astype(np.int64).reshape(-1)
    fe = np.asarray(face_edges, dtype=np.int64).reshape(-1)
    # the widest face of the edge decides (its fewest points)
    counts[:] = MAX_STEINER + 1
    np.minimum.at(counts, fe, want)
    counts[counts > MAX_STEINER] = k
    if face_ok is not None:
        # edges of graph-only faces (degenerate: no window crosses them, paths bend at their nodes): closer nodes
        bad = np.asarray(face_edges)[np.asarray(face_ok) == 0].reshape(-1)
        if len(bad):
            counts[bad] = np.maximum(counts[bad], min(GRAPH_ONLY_FACTOR * k, MAX_STEINER))
    return counts
