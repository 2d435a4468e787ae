"""Reference geodesic distances for the solver's tests (CPU, float64).

- `steiner_dijkstra`: scipy Dijkstra on the explicit Steiner graph the solver relaxes (the solver with its
  unfolding windows off must give the same values, with them on never larger).
- `exact_distances`: exact polyhedral geodesic distances (tvb-gdist, Kirsanov's MMP) on meshes that are not
  manifolds. gdist is exact on a manifold but misses paths through a vertex whose faces form several fans and
  through edges with three or more faces, so the mesh is cut into a manifold first (every vertex split into one
  copy per fan, every non-manifold edge cut so each of its faces keeps its own copy), and the cut places become
  portals: all copies of a split vertex, and `samples` points along each cut edge inserted into its faces
  (the surface is unchanged). A path may jump between copies of one portal; the distance is the shortest
  combination, found by Dijkstra over the portals. Across an edge portal the crossing point is sampled, so the
  value is an upper bound that shrinks with the square of the spacing. Measured as the solver's lowest value
  relative to it (the solver is never below exact beyond float32 rounding): ellipsoid with four fins 6.6e-5
  with 32 samples, 5e-6 with 128; the tests' coarser one-fin ellipsoid 1.1e-5 with 128, 5e-7 with 512. The
  tests use 256.
"""
from __future__ import annotations

import numpy as np

from neurogf_warp.ground_truth.geodesics import DEFAULT_K
from neurogf_warp.mesh.mesh import load_mesh


def steiner_graph(mesh, k: int):
    """The explicit Steiner graph (scipy CSR, float64 weights in normalized units) that the solver relaxes."""
    import scipy.sparse as sp

    from neurogf_warp.ground_truth.steiner_graph import Topology

    m = load_mesh(mesh)
    pos = m.internal_normalized_vertices
    # the solver's own tables (its Steiner points per edge, k or more on thin faces), on the same positions
    topo = Topology(pos.astype(np.float32), m.internal_faces)
    start, node_edge, node_t = topo.steiner_nodes(k)
    nv = len(pos)
    e0, e1 = pos[topo.edges[node_edge, 0]], pos[topo.edges[node_edge, 1]]
    epts = e0 + node_t[:, None].astype(np.float64) * (e1 - e0)
    allpos = np.concatenate([pos, epts])
    F = len(topo.faces)
    counts = np.diff(start)
    per_face = [np.concatenate([topo.faces[f]] + [nv + start[e] + np.arange(counts[e]) for e in topo.face_edges[f]])
                for f in range(F)]
    a_list, b_list = [], []
    for sl in per_face:
        i, j = np.triu_indices(len(sl), 1)
        a_list.append(sl[i])
        b_list.append(sl[j])
    a = np.concatenate(a_list)
    b = np.concatenate(b_list)
    w = np.linalg.norm(allpos[a] - allpos[b], axis=1)
    n = nv + len(node_edge)
    # a node pair on two faces would be summed by the sparse constructor: keep one copy
    key = np.minimum(a, b).astype(np.int64) * n + np.maximum(a, b)
    _, first = np.unique(key, return_index=True)
    g = sp.coo_matrix((w[first], (a[first], b[first])), shape=(n, n)).tocsr()
    return g + g.T, nv


def steiner_dijkstra(mesh, sources, k: int = DEFAULT_K) -> np.ndarray:
    """Plain CPU Dijkstra (scipy) on the solver's Steiner graph: (S, V_input) float32 distances, mesh units."""
    from scipy.sparse.csgraph import dijkstra

    m = load_mesh(mesh)
    src = np.atleast_1d(m.vertex(np.asarray(sources)))
    g, nv = steiner_graph(m, k)
    d = dijkstra(g, directed=False, indices=src)[:, :nv] / m.scale
    return m.to_input(d.astype(np.float32))


# ---- exact distances on non-manifold meshes ---------------------------------------------------------------------
def _find(parent, i):
    while parent[i] != i:
        parent[i] = parent[parent[i]]
        i = parent[i]
    return i


def manifold_cut(V, F, samples: int = 32):
    """Cut a mesh into a manifold: returns (V2, F2, original vertex of each new vertex (-1 for edge samples),
    portals: list of int arrays, each the copies of one point where paths may jump)."""
    V = np.asarray(V, dtype=np.float64)
    F = np.asarray(F, dtype=np.int64)
    half = np.sort(np.stack([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]], 1).reshape(-1, 2), axis=1)
    edges, inv, count = np.unique(half, axis=0, return_inverse=True, return_counts=True)
    inv = inv.reshape(-1, 3)
    # corners (face, slot) joined around a vertex through the manifold edges (exactly two faces)
    parent = list(range(3 * len(F)))
    faces_of = {}
    for f in range(len(F)):
        for le in range(3):
            faces_of.setdefault(int(inv[f, le]), []).append((f, le))
    for e, fl in faces_of.items():
        if count[e] != 2:
            continue
        (f1, l1), (f2, l2) = fl
        for v in edges[e]:
            c1 = 3 * f1 + int(np.where(F[f1] == v)[0][0])
            c2 = 3 * f2 + int(np.where(F[f2] == v)[0][0])
            parent[_find(parent, c1)] = _find(parent, c2)
    roots = np.array([_find(parent, c) for c in range(3 * len(F))])
    uniq, newid = np.unique(roots, return_inverse=True)
    F2 = newid.reshape(-1, 3).astype(np.int64)
    orig = np.empty(len(uniq), dtype=np.int64)
    orig[newid] = F.reshape(-1)
    V2 = V[orig]
    portals = [np.where(orig == v)[0] for v in np.unique(orig) if np.sum(orig == v) > 1]
    # every cut edge: samples along each distinct copy, inserted into the faces holding that copy
    t = (np.arange(samples) + 1.0) / (samples + 1.0)
    cut = []  # (a, b, distinct copies (pa, pb) of the edge), read before any face is split
    for e in np.where(count > 2)[0]:
        a, b = edges[e]
        copies = {}
        for f, le in faces_of[int(e)]:
            pa, pb = F2[f, le], F2[f, (le + 1) % 3]
            if orig[pa] == b:
                pa, pb = pb, pa
            copies.setdefault((int(pa), int(pb)), None)
        cut.append((a, b, list(copies)))
    for a, b, copies in cut:
        groups = []
        for (pa, pb) in copies:
            ids = len(V2) + np.arange(samples)
            V2 = np.concatenate([V2, V[a] + t[:, None] * (V[b] - V[a])])
            orig = np.concatenate([orig, np.full(samples, -1)])
            groups.append(ids)
            hit = np.where(np.isin(F2, [pa, pb]).sum(1) == 2)[0]
            new, keep = [], np.ones(len(F2), bool)
            for f in hit:
                row = F2[f]
                i = int(np.where(row == pa)[0][0])
                j = int(np.where(row == pb)[0][0])
                c = row[3 - i - j]
                chain = np.r_[pa, ids, pb] if (j - i) % 3 == 1 else np.r_[pb, ids[::-1], pa]
                new += [[chain[q], chain[q + 1], c] for q in range(len(chain) - 1)]
                keep[f] = False
            F2 = np.concatenate([F2[keep], np.array(new, dtype=np.int64)])
        portals += [np.array([g[j] for g in groups]) for j in range(samples)]
    return V2, F2, orig, portals


def exact_distances(V, F, sources, samples: int = 32) -> np.ndarray:
    """(S, n) float64 exact geodesic distances from vertex ids `sources` on a mesh with non-manifold vertices
    and edges (see the module docstring); inf between components. Meshes must use every vertex."""
    import gdist
    from scipy.sparse.csgraph import dijkstra

    V2, F2, orig, portals = manifold_cut(V, F, samples)
    f32 = F2.astype(np.int32)

    def solve(seeds):
        return gdist.compute_gdist(V2, f32, source_indices=np.asarray(seeds, dtype=np.int32))

    P = np.array([solve(p) for p in portals]) if portals else np.zeros((0, len(V2)))
    members = np.concatenate(portals) if portals else np.zeros(0, np.int64)
    starts = np.r_[0, np.cumsum([len(p) for p in portals])[:-1]].astype(np.int64)

    def to_portals(d):  # (..., n2) -> (..., portals): the nearest copy of each portal
        return np.minimum.reduceat(d[..., members], starts, axis=-1)

    between = to_portals(P) if portals else P
    n = len(V)
    out = np.empty((len(np.atleast_1d(sources)), n))
    for r, s in enumerate(np.atleast_1d(sources)):
        d0 = solve(np.where(orig == s)[0])
        if len(portals):
            first = to_portals(d0)
            g = np.zeros((len(portals) + 1, len(portals) + 1))
            g[0, 1:] = first
            g[1:, 1:] = between
            # dense csgraph input: 0 means no edge, so a zero-length jump gets a negligible positive weight
            g = np.where(np.isfinite(g), np.maximum(g, 1e-300), 0.0)
            reach = dijkstra(g, directed=True, indices=0)[1:]
            d0 = np.minimum(d0, np.min(reach[:, None] + P, axis=0))
        d = np.full(n, np.inf)
        np.minimum.at(d, orig[orig >= 0], d0[orig >= 0])
        out[r] = d
    return out


def gdist_distances(V, F, sources) -> np.ndarray:
    """(S, V) exact polyhedral distances from tvb-gdist (MMP, float64) on the mesh as given; inf unreachable."""
    import gdist

    V = np.ascontiguousarray(V, dtype=np.float64)
    F = np.ascontiguousarray(F, dtype=np.int32)
    out = np.stack([gdist.compute_gdist(V, F, source_indices=np.array([s], np.int32)) for s in np.atleast_1d(sources)])
    out[out >= np.finfo(np.float64).max / 2] = np.inf
    return out
