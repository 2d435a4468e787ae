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

from .graph import (
    INF,
    SteinerGraph,
    face_has_node,
    face_normal_in_plane64,
    node_pos,
    other_face,
    position64,
    steiner_edge,
)
from .relax import NodeState, PathRecords
from .unfolding import unfold_source

wp.set_module_options({"enable_backward": False, "fuse_fp": False})

MAX_CHOICES = wp.constant(64)  # face choices tried per ray at non-manifold crossings


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
def unfold_point(graph: SteinerGraph, e: int, face: int, S: wp.vec3d) -> wp.vec3d:
    """Point S (in the plane of a face on one side of edge e) rotated about e into the plane of `face`."""
    A = position64(graph, graph.edges[e, 0])
    ev = position64(graph, graph.edges[e, 1]) - A
    eh = ev / wp.length(ev)
    r = S - A
    return A + wp.dot(r, eh) * eh + wp.length(wp.cross(r, eh)) * face_normal_in_plane64(graph, e, face)


@wp.func
def walk_ray(graph: SteinerGraph, cur: int, o: int, g: int, S_in: wp.vec3, max_steps: int, choice: int,
             q: PathQuery, write: int, at: int):
    """Walk the straight unfolded ray from node cur (in face g) towards the virtual source S_in until the face
    holding the origin o, where the unfolded source must land on o (else the walk went wrong). float64 inside,
    so thin faces (thin in float32 too) are crossed like any other.

    On a non-manifold edge the face the ray came from is not known: `choice` picks one (its digits in the mixed
    radix of the candidate counts, one digit per such crossing), and the caller tries the choices in turn.
    Returns (number of crossing points (written at q.points[at...] when write = 1), vertex, choices, length):
    vertex = -1 when the walk reached o; (n, v) when the walk stopped (circling, no exit, a boundary, a
    graph-only face) with its last crossing point on mesh vertex v (the ray ran through v within rounding): the
    caller ends the ray at v and goes on along v's own path; n = -1 when the walk fails. choices: how many choice
    values the crossings met on this walk allow (1 on a manifold). length: of the walk from cur to v."""
    zero = wp.float64(0.0)
    one = wp.float64(1.0)
    S = wp.vec3d(S_in)
    n = int(0)
    steps = int(0)
    Q = wp.vec3d(node_pos(graph, cur))
    face = g
    ray_len = wp.length(S - Q)
    walked = zero
    digits = choice
    choices = int(1)
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
        p0 = position64(graph, graph.faces[face, 0])
        p1 = position64(graph, graph.faces[face, 1])
        p2 = position64(graph, graph.faces[face, 2])
        nrm = wp.cross(p1 - p0, p2 - p0)
        dv = S - Q
        # tolerances in units of the face's size (thin faces are crossed in small steps), as ray parameters
        size = wp.max(wp.length(p1 - p0), wp.max(wp.length(p2 - p1), wp.length(p0 - p2)))
        dv_len = wp.max(wp.length(dv), wp.float64(1.0e-300))
        behind = wp.float64(1.0e-7) * size / dv_len
        best_t = wp.float64(2.0)
        best_le = int(-1)
        best_w = zero
        for le in range(3):
            ed = graph.face_edges[face, le]
            if ed == ex0 or ed == ex1:
                continue
            B0 = position64(graph, graph.faces[face, le])
            evl = position64(graph, graph.faces[face, (le + 1) % 3]) - B0
            den = wp.dot(wp.cross(dv, evl), nrm)
            if wp.abs(den) <= zero:
                continue
            tt = wp.dot(wp.cross(B0 - Q, evl), nrm) / den
            ww = wp.dot(wp.cross(B0 - Q, dv), nrm) / den
            if tt > -behind and ww >= wp.float64(-1.0e-4) and ww <= wp.float64(1.0001) and tt < best_t:
                best_t = tt
                best_le = le
                best_w = ww
        if best_le < 0:
            break
        if best_t * dv_len <= wp.float64(1.0e-9) * size:
            # no progress: the ray passes (within rounding) through a vertex of this face and circles it
            break
        if best_t >= wp.float64(1.0 - 1.0e-5):
            ok = True  # the virtual source (the origin node) lies on this face's boundary
            break
        ed = graph.face_edges[face, best_le]
        B0 = position64(graph, graph.faces[face, best_le])
        Q_next = B0 + wp.clamp(best_w, zero, one) * (position64(graph, graph.faces[face, (best_le + 1) % 3]) - B0)
        walked += wp.length(Q_next - Q)
        Q = Q_next
        if write != 0:
            q.points[at + n] = wp.vec3(Q)
        n += 1
        nfaces = graph.edge_face_start[ed + 1] - graph.edge_face_start[ed]
        nf = other_face(graph, ed, face, digits)
        if nfaces > 2:
            digits = digits // (nfaces - 1)
            choices = choices * (nfaces - 1)
        if nf < 0 or graph.window_face[nf] == wp.int8(0):
            break  # windows never cross graph-only faces: the walk has strayed (or left through a vertex)
        S = unfold_point(graph, ed, nf, S)
        face = nf
        ex0 = ed
        ex1 = int(-1)
    if ok:
        miss = wp.length(S - wp.vec3d(node_pos(graph, o)))
        if digits != 0 or miss > wp.float64(1.0e-4) * ray_len + wp.float64(1.0e-6):
            # a choice left unused repeats a smaller one; a source landing off the origin: wrong faces
            return int(-1), int(-1), choices, float(walked)
        return n, int(-1), choices, float(walked)
    # The ray left through (or circles) a vertex within rounding: end it at that vertex (it lies on the ray, so
    # its own distance is at most the ray's value there) when Q is on it; otherwise fail (the caller bends at the
    # parent).
    lmax = zero
    dbest = wp.float64(1.0e300)
    for lv in range(3):
        pv = position64(graph, graph.faces[face, lv])
        lmax = wp.max(lmax, wp.length(position64(graph, graph.faces[face, (lv + 1) % 3]) - pv))
        dq = wp.length(pv - Q)
        if dq < dbest and graph.faces[face, lv] != cur:
            dbest = dq
            snap = graph.faces[face, lv]
    if n > 0 and snap >= 0 and dbest <= wp.float64(1.0e-3) * lmax and digits == 0:
        return n, snap, choices, float(walked + dbest)
    return int(-1), int(-1), choices, float(walked)


@wp.kernel
def walk_paths(graph: SteinerGraph, rec: PathRecords, dist: wp.array2d(dtype=float), q: PathQuery):
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
        # try the face choices at non-manifold crossings until one walk lands on the origin; of the walks that
        # end at a vertex they ran through (a wrong sheet can pass a vertex too) the shortest path is kept
        m = int(-1)
        snap = int(-1)
        best = int(-1)
        best_len = float(INF)
        choice = int(0)
        limit = int(1)
        while choice < wp.min(limit, MAX_CHOICES):
            mc, sc, allowed, walked = walk_ray(graph, cur, o, g, S, q.max_steps, choice, q, 0, 0)
            limit = wp.max(limit, allowed)
            if mc >= 0 and sc < 0:
                m = mc
                snap = sc
                best = choice
                break
            if mc >= 0 and walked + dist[s, sc] < best_len:
                best_len = walked + dist[s, sc]
                m = mc
                snap = sc
                best = choice
            choice += 1
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
            walk_ray(graph, cur, o, g, S, q.max_steps, best, q, 1, base + n)
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


@wp.func
def polyline_point(points: wp.array(dtype=wp.vec3), a: int, b: int, k: int, reverse: int) -> wp.vec3:
    """Point k (a <= k < b) of the polyline points[a:b], read backwards when ``reverse`` (the walk writes
    target -> source; datasets want source -> target)."""
    if reverse != 0:
        return points[a + b - 1 - k]
    return points[k]


@wp.func
def polyline_length64(points: wp.array(dtype=wp.vec3), a: int, b: int, reverse: int) -> wp.float64:
    """Float64 length of points[a:b], summed segment by segment in reading order."""
    length = wp.float64(0.0)
    for k in range(a + 1, b):
        length += wp.length(wp.vec3d(polyline_point(points, a, b, k, reverse))
                            - wp.vec3d(polyline_point(points, a, b, k - 1, reverse)))
    return length


@wp.func
def resample_one(points: wp.array(dtype=wp.vec3), a: int, b: int, reverse: int, out: wp.array2d(dtype=wp.vec3),
                 i: int):
    """Row i of ``out``: polyline points[a:b] (backwards when ``reverse``) resampled to m = out.shape[1] points
    equally spaced by arc length (float64 arc lengths accumulated point by point; sample k at k / (m - 1) of the
    length, on the last segment whose start is at or before it). No points or a non-finite one: a NaN row; one
    point: that point m times. One walk along the polyline serves all m samples (they come in order)."""
    m = out.shape[1]
    length = polyline_length64(points, a, b, reverse)
    if b <= a:
        for k in range(m):
            out[i, k] = wp.vec3(wp.nan, wp.nan, wp.nan)
        return
    first = polyline_point(points, a, b, a, reverse)
    if not wp.isfinite(length) or not wp.isfinite(first):
        for k in range(m):
            out[i, k] = wp.vec3(wp.nan, wp.nan, wp.nan)
        return
    if b - a == 1:
        for k in range(m):
            out[i, k] = first
        return
    j = a  # segment j -> j + 1, starting at arc length s
    s = wp.float64(0.0)
    seg = wp.length(wp.vec3d(polyline_point(points, a, b, a + 1, reverse)) - wp.vec3d(first))
    for k in range(m):
        t = length * (wp.float64(k) / wp.float64(m - 1))
        while j < b - 2 and s + seg <= t:
            s += seg
            j += 1
            seg = wp.length(wp.vec3d(polyline_point(points, a, b, j + 1, reverse))
                            - wp.vec3d(polyline_point(points, a, b, j, reverse)))
        w = wp.float64(0.0)
        if seg > wp.float64(0.0):
            w = (t - s) / seg
        p = wp.vec3d(polyline_point(points, a, b, j, reverse))
        out[i, k] = wp.vec3(p + w * (wp.vec3d(polyline_point(points, a, b, j + 1, reverse)) - p))


@wp.kernel
def resample_by_length(points: wp.array(dtype=wp.vec3), starts: wp.array(dtype=int), ends: wp.array(dtype=int),
                       out: wp.array2d(dtype=wp.vec3)):
    """Thread i: polyline points[starts[i]:ends[i]] resampled to out.shape[1] points (``resample_one``)."""
    i = wp.tid()
    resample_one(points, starts[i], ends[i], 0, out, i)


@wp.kernel
def check_walks(q: PathQuery, dist: wp.array2d(dtype=float), rel_tol: wp.float64, abs_tol: wp.float64,
                flags: wp.array(dtype=int)):
    """Thread t: path t of a written walk (``walk_paths``) flagged -1 when truncated at max_steps, 1 when its
    float64 length exceeds its node's distance by more than rel_tol (relative) and abs_tol, else 0."""
    t = wp.tid()
    flag = int(0)
    if q.stale[t] < 0:
        flag = -1
    else:
        a = q.offsets[t]
        d = wp.float64(dist[q.rows[t], q.targets[t]])
        length = polyline_length64(q.points, a, a + q.counts[t], 1)
        if wp.isfinite(d) and length > d * (wp.float64(1.0) + rel_tol) + abs_tol:
            flag = 1
    flags[t] = flag


@wp.kernel
def resample_walks(q: PathQuery, flags: wp.array(dtype=int), out: wp.array2d(dtype=wp.vec3)):
    """Row t: path t of a written walk, source first, resampled by ``resample_one``; a flagged path gives a NaN
    row."""
    t = wp.tid()
    if flags[t] != 0:
        for k in range(out.shape[1]):
            out[t, k] = wp.vec3(wp.nan, wp.nan, wp.nan)
        return
    a = q.offsets[t]
    resample_one(q.points, a, a + q.counts[t], 1, out, t)
