"""Shortest paths from the path records, and distances made equal to the paths' lengths.

Node x's path record (relax.PathRecords): its origin o (the node its straight unfolded ray, or its graph edge,
goes back to) and, for a ray, the virtual source (ray_along, ray_height) in the frame of its parent's edge,
unfolded into the face ray_face. The record never changes after x's last improvement, but o may have improved
later (then x's distance is longer than o's current distance + the straight piece). The slack of x is
d_x - (d_o + straight piece) >= 0; pointer jumping sums it along the origin chain, and d_x - (the sum) is exactly
the length of the polyline the tracer walks (the same or shorter: still an upper bound of the exact distance).

The tracer walks back from a target: a graph edge goes straight to the parent; a ray walks straight towards its
virtual source face by face (unfolding the source across each crossed edge) and ends at the record's origin.
"""
import warp as wp

from .graph import (INF, SteinerGraph, edge_frame, face_has_node, face_normal_in_plane, node_pos, steiner_edge)
from .relax import NodeState, PathRecords
from .unfolding import unfold_source

wp.set_module_options({"enable_backward": False, "fuse_fp": False})


@wp.struct
class PathQuery:
    """Paths to trace: row and target per path; outputs per path and the points (target -> source order)."""

    rows: wp.array(dtype=int)  # (T,) source row of each path
    targets: wp.array(dtype=int)  # (T,) target node
    offsets: wp.array(dtype=int)  # (T,) first point of each path in `points` (write pass)
    points: wp.array(dtype=wp.vec3)  # written when write = 1
    counts: wp.array(dtype=int)  # (T,) points of each path
    stale: wp.array(dtype=int)  # (T,) ray walks that failed (bent at the parent); -1: truncated at max_steps
    max_steps: int
    write: int  # 0: count the points only


@wp.func
def record_length(graph: SteinerGraph, rec: PathRecords, s: int, x: int) -> float:
    """Length of the straight piece of x's record: to the ray's virtual source, or to the parent."""
    px = node_pos(graph, x)
    par = rec.parent[s, x]
    if rec.ray_face[s, x] >= 0:
        source = unfold_source(graph, steiner_edge(graph, par), rec.ray_face[s, x], rec.ray_along[s, x],
                               rec.ray_height[s, x])
        return wp.length(source - px)
    return wp.length(px - node_pos(graph, par))


@wp.kernel
def slack_init(graph: SteinerGraph, state: NodeState, ptr: wp.array2d(dtype=int), acc: wp.array2d(dtype=float)):
    s, x = wp.tid()
    par = state.rec.parent[s, x]
    if par < 0 or par == x or not (state.dist[s, x] < INF):
        ptr[s, x] = x
        acc[s, x] = 0.0
        return
    o = state.rec.origin[s, x]
    ptr[s, x] = o
    sl = state.dist[s, x] - (state.dist[s, o] + record_length(graph, state.rec, s, x))
    acc[s, x] = wp.max(sl, 0.0)


@wp.kernel
def slack_jump(ptr: wp.array2d(dtype=int), acc: wp.array2d(dtype=float), ptr2: wp.array2d(dtype=int),
               acc2: wp.array2d(dtype=float)):
    s, x = wp.tid()
    p = ptr[s, x]
    acc2[s, x] = acc[s, x] + acc[s, p]
    ptr2[s, x] = ptr[s, p]


@wp.kernel
def slack_apply(acc: wp.array2d(dtype=float), dist: wp.array2d(dtype=float)):
    s, x = wp.tid()
    a = acc[s, x]
    if a > 0.0:
        dist[s, x] = dist[s, x] - a


@wp.func
def unfold_point(graph: SteinerGraph, e: int, face: int, S: wp.vec3) -> wp.vec3:
    """Point S (in the plane of a face on one side of edge e) rotated about e into the plane of `face`."""
    A, eh, elen = edge_frame(graph, e)
    r = S - A
    n = face_normal_in_plane(graph, e, face, A, eh)
    return A + wp.dot(r, eh) * eh + wp.length(wp.cross(r, eh)) * n


@wp.func
def walk_ray(graph: SteinerGraph, cur: int, o: int, g: int, S_in: wp.vec3, max_steps: int, q: PathQuery, write: int,
             at: int):
    """Walk the straight unfolded ray from node cur (in face g) towards the virtual source S_in until the face
    holding the origin o. Returns (number of crossing points (written at q.points[at...] when write = 1),
    vertex): vertex = -1 when the walk reached the origin's face; (n, v) when the walk stopped (circling, no exit,
    a boundary, a graph-only face) with its last crossing point on mesh vertex v (the ray ran through v within
    rounding): the caller ends the ray at v and goes on along v's own path; (-1, -1) when the walk fails."""
    S = S_in
    n = int(0)
    steps = int(0)
    Q = node_pos(graph, cur)
    face = g
    # edges the walk must not leave through: those holding the start point, then the entry edge
    ex0 = int(-1)
    ex1 = int(-1)
    if cur >= graph.nv:
        ex0 = steiner_edge(graph, cur)
    else:
        for le in range(3):
            if graph.faces[g, le] == cur or graph.faces[g, (le + 1) % 3] == cur:
                if ex0 < 0:
                    ex0 = graph.face_edges[g, le]
                else:
                    ex1 = graph.face_edges[g, le]
    ok = bool(False)
    snap = int(-1)
    while steps < max_steps:
        steps += 1
        if face_has_node(graph, face, o):
            ok = True  # the origin is on this face: the rest of the ray is the straight segment to it
            break
        p0 = graph.pos[graph.faces[face, 0]]
        nrm = wp.cross(graph.pos[graph.faces[face, 1]] - p0, graph.pos[graph.faces[face, 2]] - p0)
        dv = S - Q
        best_t = float(2.0)
        best_le = int(-1)
        best_w = float(0.0)
        for le in range(3):
            ed = graph.face_edges[face, le]
            if ed == ex0 or ed == ex1:
                continue
            B0 = graph.pos[graph.faces[face, le]]
            evl = graph.pos[graph.faces[face, (le + 1) % 3]] - B0
            den = wp.dot(wp.cross(dv, evl), nrm)
            if wp.abs(den) <= 0.0:
                continue
            tt = wp.dot(wp.cross(B0 - Q, evl), nrm) / den
            ww = wp.dot(wp.cross(B0 - Q, dv), nrm) / den
            if tt > -1.0e-4 and ww >= -1.0e-4 and ww <= 1.0001 and tt < best_t:
                best_t = tt
                best_le = le
                best_w = ww
        if best_le < 0:
            break
        if best_t <= 1.0e-6:
            # no progress: the ray passes (within rounding) through a vertex of this face and circles it
            break
        if best_t >= 1.0 - 1.0e-5:
            ok = True  # the virtual source (the origin node) lies on this face's boundary
            break
        ed = graph.face_edges[face, best_le]
        B0 = graph.pos[graph.faces[face, best_le]]
        Q = B0 + wp.clamp(best_w, 0.0, 1.0) * (graph.pos[graph.faces[face, (best_le + 1) % 3]] - B0)
        if write != 0:
            q.points[at + n] = Q
        n += 1
        f0 = graph.edge_faces[ed, 0]
        nf = graph.edge_faces[ed, 1]
        if f0 != face:
            nf = f0
        if nf < 0 or nf == face or graph.window_face[nf] == wp.int8(0):
            break  # windows never cross graph-only faces: the walk has strayed (or left through a vertex)
        S = unfold_point(graph, ed, nf, S)
        face = nf
        ex0 = ed
        ex1 = int(-1)
    if not ok:
        # The ray left through (or circles) a vertex within rounding: end it at that vertex (it lies on the ray, so
        # its own distance is at most the ray's value there) when Q is on it; otherwise fail (the caller bends at
        # the parent).
        lmax = float(0.0)
        dbest = float(INF)
        for lv in range(3):
            pv = graph.pos[graph.faces[face, lv]]
            lmax = wp.max(lmax, wp.length(graph.pos[graph.faces[face, (lv + 1) % 3]] - pv))
            dq = wp.length(pv - Q)
            if dq < dbest and graph.faces[face, lv] != cur:
                dbest = dq
                snap = graph.faces[face, lv]
        if n > 0 and snap >= 0 and dbest <= 1.0e-3 * lmax:
            return n, snap
        return int(-1), int(-1)
    return n, int(-1)


@wp.kernel
def walk_paths(graph: SteinerGraph, rec: PathRecords, q: PathQuery):
    """Walk each path back from its target to the source along the path records (target -> source order)."""
    t = wp.tid()
    s = q.rows[t]
    cur = q.targets[t]
    base = int(0)
    if q.write != 0:
        base = q.offsets[t]
    if rec.parent[s, cur] < 0:
        q.counts[t] = 0
        q.stale[t] = 0
        return
    if q.write != 0:
        q.points[base] = graph.pos[cur]
    n = int(1)
    nstale = int(0)
    done = bool(False)
    steps = int(0)
    while steps < q.max_steps:
        steps += 1
        par = rec.parent[s, cur]
        if par == cur:
            done = True
            break
        g = rec.ray_face[s, cur]
        o = rec.origin[s, cur]
        if g < 0:
            if q.write != 0:
                q.points[base + n] = node_pos(graph, par)
            n += 1
            cur = par
            continue
        S = unfold_source(graph, steiner_edge(graph, par), g, rec.ray_along[s, cur], rec.ray_height[s, cur])
        m, snap = walk_ray(graph, cur, o, g, S, q.max_steps, q, 0, 0)
        if m < 0:
            # numerically failed walk: bend at the parent (shares face g with cur) and go on from there
            nstale += 1
            if q.write != 0:
                q.points[base + n] = node_pos(graph, par)
            n += 1
            cur = par
            continue
        steps += m
        if q.write != 0:
            walk_ray(graph, cur, o, g, S, q.max_steps, q, 1, base + n)
        n += m
        nxt = o
        if snap >= 0:
            nxt = snap  # the ray ran through vertex snap: go on along its own path
        if q.write != 0:
            q.points[base + n] = node_pos(graph, nxt)
        n += 1
        cur = nxt
    q.counts[t] = n
    if not done:
        nstale = -1
    q.stale[t] = nstale
