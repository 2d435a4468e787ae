"""Warp kernels of the geodesic solver: Steiner-point graph + one-window-per-node unfolding.

Nodes: the V mesh vertices, then k Steiner points per unique edge (node V + e*k + j sits at
t = (j+1)/(k+1) from the edge's lower vertex to its higher one). The graph is never stored: a face's
boundary nodes (3 vertices + 3k edge points) are all joined to each other, so relaxing face by face
visits every graph edge.

Each node carries, besides its distance, a "window": a virtual source S (in the edge's frame: `a` along
the edge from its lower vertex, `h` away from the line on the side of `in_face`), the distance `sigma`
at S, and an interval [L, R] (edge parameters) of the node's edge through which straight rays from S
are known to be real surface paths (unfolded across the faces crossed). Crossing into the next face,
the ray from S continues straight (exact unfolding) as long as it crosses the edge inside [L, R].
Every candidate distance is the length of a real surface path, so all values are upper bounds of the
exact geodesic distance; with windows off it is the plain Steiner graph.

Candidates are proposed with a uint64 atomic_min on (float bits << 32 | parent node); a second pass
re-derives the winner's window from the parent (read from the committed state, so it is consistent),
a third commits. Per (source row, node) arrays have shape (S, N).
"""
import warp as wp

wp.set_module_options({"enable_backward": False, "fuse_fp": False})

INF = wp.constant(float("inf"))
NOPARENT = wp.constant(wp.uint32(0xFFFFFFFF))
TINY = wp.constant(1.0e-12)


@wp.func
def pack(d: float, parent: int) -> wp.uint64:
    return (wp.uint64(wp.cast(d, wp.uint32)) << wp.uint64(32)) | wp.uint64(wp.uint32(parent))


@wp.func
def unpack_dist(key: wp.uint64) -> float:
    return wp.cast(wp.uint32(key >> wp.uint64(32)), float)


@wp.func
def unpack_parent(key: wp.uint64) -> int:
    return int(wp.uint32(key & wp.uint64(0xFFFFFFFF)))


@wp.func
def node_edge(n: int, nv: int, k: int) -> int:
    if n < nv:
        return -1
    return (n - nv) // k


@wp.func
def node_pos(n: int, nv: int, k: int, pos: wp.array(dtype=wp.vec3), edges: wp.array2d(dtype=int)) -> wp.vec3:
    if n < nv:
        return pos[n]
    m = n - nv
    e = m // k
    j = m - e * k
    t = float(j + 1) / float(k + 1)
    a = pos[edges[e, 0]]
    b = pos[edges[e, 1]]
    return a + t * (b - a)


@wp.func
def slot_node(g: int, i: int, nv: int, k: int, faces: wp.array2d(dtype=int), face_edges: wp.array2d(dtype=int)) -> int:
    if i < 3:
        return faces[g, i]
    le = (i - 3) // k
    return nv + face_edges[g, le] * k + (i - 3 - le * k)


@wp.func
def slots_share_edge(i: int, j: int, k: int) -> bool:
    # local edge le joins face vertices le and (le+1)%3; vertex slot i lies on edges i and (i+2)%3
    ei0 = i
    ei1 = (i + 2) % 3
    if i >= 3:
        ei0 = (i - 3) // k
        ei1 = ei0
    ej0 = j
    ej1 = (j + 2) % 3
    if j >= 3:
        ej0 = (j - 3) // k
        ej1 = ej0
    return ei0 == ej0 or ei0 == ej1 or ei1 == ej0 or ei1 == ej1


@wp.func
def face_has_node(g: int, n: int, nv: int, k: int, faces: wp.array2d(dtype=int), face_edges: wp.array2d(dtype=int)) -> bool:
    if n < nv:
        return faces[g, 0] == n or faces[g, 1] == n or faces[g, 2] == n
    e = (n - nv) // k
    return face_edges[g, 0] == e or face_edges[g, 1] == e or face_edges[g, 2] == e


@wp.func
def common_face(u: int, x: int, nv: int, k: int, faces: wp.array2d(dtype=int), face_edges: wp.array2d(dtype=int),
                edge_faces: wp.array2d(dtype=int)) -> int:
    """The face holding nodes u and x: >= 0, -2 when they share an edge (or are both vertices), -1 if none."""
    e = -1
    other = u
    if x >= nv:
        e = (x - nv) // k
    elif u >= nv:
        e = (u - nv) // k
        other = x
    else:
        return -2
    f0 = edge_faces[e, 0]
    f1 = edge_faces[e, 1]
    c0 = False
    c1 = False
    if f0 >= 0:
        c0 = face_has_node(f0, other, nv, k, faces, face_edges)
    if f1 >= 0:
        c1 = face_has_node(f1, other, nv, k, faces, face_edges)
    if c0 and c1:
        return -2
    if c0:
        return f0
    if c1:
        return f1
    return -1


@wp.func
def opposite_vertex(g: int, e: int, faces: wp.array2d(dtype=int), edges: wp.array2d(dtype=int)) -> int:
    a = edges[e, 0]
    b = edges[e, 1]
    c = faces[g, 0]
    if c == a or c == b:
        c = faces[g, 1]
        if c == a or c == b:
            c = faces[g, 2]
    return c


@wp.func
def window_dist(a: float, h: float, sigma: float, wl: float, wr: float, A: wp.vec3, eh: wp.vec3, elen: float,
                p: wp.vec3) -> float:
    """Length of the straight unfolded ray from the virtual source (a, -h) to p (on the other side of the edge),
    or inf when the ray does not cross the edge inside the window [wl, wr]."""
    r = p - A
    ax = wp.dot(r, eh)
    hx = wp.length(wp.cross(r, eh))
    if hx <= TINY * elen:
        return INF
    c = (a + (ax - a) * h / (h + hx)) / elen
    if c < wl or c > wr:
        return INF
    dx = ax - a
    dy = hx + h
    return sigma + wp.sqrt(dx * dx + dy * dy)


@wp.func
def in_plane_normal(A: wp.vec3, eh: wp.vec3, C: wp.vec3) -> wp.vec3:
    w = C - A
    n = w - wp.dot(w, eh) * eh
    ln = wp.length(n)
    if ln <= 0.0:
        return wp.vec3(0.0, 0.0, 0.0)
    return n / ln


@wp.func
def edge_frame(e: int, pos: wp.array(dtype=wp.vec3), edges: wp.array2d(dtype=int)):
    """Frame of edge e: its lower vertex A, unit direction eh and length elen."""
    A = pos[edges[e, 0]]
    ev = pos[edges[e, 1]] - A
    elen = wp.length(ev)
    return A, ev / elen, elen


@wp.func
def face_candidate(s: int, u: int, du: float, pu: wp.vec3, iu: int, j: int, g: int, win: bool, A: wp.vec3,
                   eh: wp.vec3, elen: float, nv: int, k: int, pos: wp.array(dtype=wp.vec3),
                   faces: wp.array2d(dtype=int), edges: wp.array2d(dtype=int), face_edges: wp.array2d(dtype=int),
                   wa: wp.array2d(dtype=float), wh: wp.array2d(dtype=float), wsig: wp.array2d(dtype=float),
                   wl: wp.array2d(dtype=float), wr: wp.array2d(dtype=float)):
    """Candidate from node u (slot iu of face g, distance du, position pu) to the node x in slot j of g: the graph
    edge, or the straight ray of u's window when shorter (win: the window continues into g; A, eh, elen: frame of
    u's edge). Returns (x, d)."""
    x = slot_node(g, j, nv, k, faces, face_edges)
    px = node_pos(x, nv, k, pos, edges)
    d = du + wp.length(px - pu)
    if win and not slots_share_edge(iu, j, k):
        dw = window_dist(wa[s, u], wh[s, u], wsig[s, u], wl[s, u], wr[s, u], A, eh, elen, px)
        if dw < d:
            d = dw
    return x, d


@wp.func
def propose(key: wp.array2d(dtype=wp.uint64), s: int, x: int, d: float, u: int) -> bool:
    """Offer node x distance d through parent u (packed atomic_min); True when this lowered x's key."""
    if d < unpack_dist(key[s, x]):
        pk = pack(d, u)
        old = wp.atomic_min(key, s, x, pk)
        return pk < old
    return False


@wp.kernel
def init_kernel(sources: wp.array(dtype=int), key: wp.array2d(dtype=wp.uint64), dist: wp.array2d(dtype=float),
                parent: wp.array2d(dtype=int), in_face: wp.array2d(dtype=int), info: wp.array2d(dtype=int),
                changed: wp.array2d(dtype=wp.int8), origin: wp.array2d(dtype=int)):
    s, n = wp.tid()
    src = sources[s]
    origin[s, n] = n
    if n == src:
        key[s, n] = pack(0.0, n)
        dist[s, n] = 0.0
        parent[s, n] = n
        changed[s, n] = wp.int8(1)
    else:
        key[s, n] = pack(INF, -1)
        dist[s, n] = INF
        parent[s, n] = -1
        changed[s, n] = wp.int8(0)
    in_face[s, n] = -1
    info[s, n] = -1


@wp.kernel
def clear_flag_kernel(cond: wp.array(dtype=int), counter: wp.array(dtype=int), thr: wp.array(dtype=float),
                      minpend: wp.array(dtype=float), delta: float):
    # delta-stepping: per source row, only nodes closer than (nearest pending distance + delta) relax.
    # Near-distance order keeps parents from changing after their children used them (consistent paths)
    # and avoids most repeated improvements of plain Bellman-Ford.
    s = wp.tid()
    thr[s] = minpend[s] + delta
    minpend[s] = INF
    if s == 0:
        counter[0] = counter[0] + 1
        cond[0] = 0


@wp.kernel
def relax_kernel(nv: int, k: int, use_windows: int, pos: wp.array(dtype=wp.vec3), faces: wp.array2d(dtype=int),
                 edges: wp.array2d(dtype=int), face_edges: wp.array2d(dtype=int), face_ok: wp.array(dtype=wp.int8),
                 dist: wp.array2d(dtype=float), in_face: wp.array2d(dtype=int),
                 wa: wp.array2d(dtype=float), wh: wp.array2d(dtype=float), wsig: wp.array2d(dtype=float),
                 wl: wp.array2d(dtype=float), wr: wp.array2d(dtype=float),
                 changed: wp.array2d(dtype=wp.int8), thr: wp.array(dtype=float), key: wp.array2d(dtype=wp.uint64)):
    s, g = wp.tid()
    ns = 3 + 3 * k
    th = thr[s]
    for i in range(ns):
        u = slot_node(g, i, nv, k, faces, face_edges)
        if changed[s, u] == wp.int8(0):
            continue
        du = dist[s, u]
        if not (du < th):
            continue
        pu = node_pos(u, nv, k, pos, edges)
        # the window of u continues into g if it arrived through another face
        win = bool(False)
        A = wp.vec3()
        eh = wp.vec3()
        elen = float(0.0)
        if use_windows != 0 and u >= nv and face_ok[g] != wp.int8(0):
            f_in = in_face[s, u]
            if f_in >= 0 and f_in != g:
                win = True
                A, eh, elen = edge_frame((u - nv) // k, pos, edges)
        for j in range(ns):
            if j == i:
                continue
            x, d = face_candidate(s, u, du, pu, i, j, g, win, A, eh, elen, nv, k, pos, faces, edges, face_edges,
                                  wa, wh, wsig, wl, wr)
            propose(key, s, x, d, u)


@wp.func
def interval_param(cq: float, ca: float, cb: float, S2: wp.vec2, elen: float, P0: wp.vec2, P1: wp.vec2) -> float:
    """Parameter t on segment P0P1 whose ray from S2 crosses the edge (y=0) at parameter cq; monotone clamp."""
    if ca <= cb:
        if cq <= ca:
            return 0.0
        if cq >= cb:
            return 1.0
    else:
        if cq >= ca:
            return 0.0
        if cq <= cb:
            return 1.0
    d = wp.vec2(cq * elen, 0.0) - S2
    e = P1 - P0
    w = P0 - S2
    den = d[0] * e[1] - d[1] * e[0]
    if wp.abs(den) <= 0.0:
        return 0.5
    t = (w[0] * d[1] - w[1] * d[0]) / den
    return wp.clamp(t, 0.0, 1.0)


@wp.func
def to_edge2(p: wp.vec3, A: wp.vec3, eh: wp.vec3) -> wp.vec2:
    r = p - A
    return wp.vec2(wp.dot(r, eh), wp.length(wp.cross(r, eh)))


@wp.func
def decode_one(s: int, x: int, nv: int, k: int, use_windows: int, pos: wp.array(dtype=wp.vec3), faces: wp.array2d(dtype=int),
                  edges: wp.array2d(dtype=int), face_edges: wp.array2d(dtype=int),
                  edge_faces: wp.array2d(dtype=int), face_ok: wp.array(dtype=wp.int8),
                  key: wp.array2d(dtype=wp.uint64), dist: wp.array2d(dtype=float), in_face: wp.array2d(dtype=int),
                  wa: wp.array2d(dtype=float), wh: wp.array2d(dtype=float), wsig: wp.array2d(dtype=float),
                  wl: wp.array2d(dtype=float), wr: wp.array2d(dtype=float),
                  improved: wp.array2d(dtype=wp.int8), n_in_face: wp.array2d(dtype=int), n_info: wp.array2d(dtype=int),
                  n_wa: wp.array2d(dtype=float), n_wh: wp.array2d(dtype=float), n_wsig: wp.array2d(dtype=float),
                  n_wl: wp.array2d(dtype=float), n_wr: wp.array2d(dtype=float),
               n_origin: wp.array2d(dtype=int), origin: wp.array2d(dtype=int), pa: wp.array2d(dtype=float),
               ph: wp.array2d(dtype=float)):
    """Decode node x's winning proposal: its new window (staged in n_*), and its path record: the origin node
    the path from x goes back to (staged in n_origin) and, when x was reached through its parent's window, that
    window's virtual source (pa, ph: in the parent edge's frame, written directly: only the tracer reads them)."""
    kk = key[s, x]
    d = unpack_dist(kk)
    if not (d < dist[s, x]):
        improved[s, x] = wp.int8(0)
        return
    improved[s, x] = wp.int8(1)
    u = unpack_parent(kk)
    orig = u
    g = common_face(u, x, nv, k, faces, face_edges, edge_faces)
    # default: x is a point source of its own (always valid: a real path of length d reaches x)
    nf = int(-1)
    a2 = float(0.0)
    h2 = float(0.0)
    sg = d
    l2 = float(0.0)
    r2 = float(1.0)
    info = int(-1)
    if g >= 0:
        px = node_pos(x, nv, k, pos, edges)
        pu = node_pos(u, nv, k, pos, edges)
        via = bool(False)
        S3 = pu
        sg = dist[s, u]
        lo = float(0.0)
        hi = float(1.0)
        if use_windows != 0 and u >= nv and face_ok[g] != wp.int8(0):
            f_in = in_face[s, u]
            if f_in >= 0 and f_in != g:
                e = (u - nv) // k
                A = pos[edges[e, 0]]
                ev = pos[edges[e, 1]] - A
                elen = wp.length(ev)
                eh = ev / elen
                ua = wa[s, u]
                uh = wh[s, u]
                dw = window_dist(ua, uh, wsig[s, u], wl[s, u], wr[s, u], A, eh, elen, px)
                if dw < sg + wp.length(px - pu):
                    via = True
                    sg = wsig[s, u]
                    ng = in_plane_normal(A, eh, pos[opposite_vertex(g, e, faces, edges)])
                    S3 = A + ua * eh - uh * ng
                    if x >= nv:
                        ex = (x - nv) // k
                        B0 = pos[edges[ex, 0]]
                        B1 = pos[edges[ex, 1]]
                        P0 = to_edge2(B0, A, eh)
                        P1 = to_edge2(B1, A, eh)
                        ca = (ua + (P0[0] - ua) * uh / (uh + P0[1])) / elen
                        cb = (ua + (P1[0] - ua) * uh / (uh + P1[1])) / elen
                        S2 = wp.vec2(ua, -uh)
                        t0 = interval_param(wl[s, u], ca, cb, S2, elen, P0, P1)
                        t1 = interval_param(wr[s, u], ca, cb, S2, elen, P0, P1)
                        lo = wp.min(t0, t1)
                        hi = wp.max(t0, t1)
        info = g * 2
        if via:
            info = info + 1
            orig = origin[s, u]
            pa[s, x] = wa[s, u]
            ph[s, x] = wh[s, u]
        if x >= nv:
            ex = (x - nv) // k
            B0 = pos[edges[ex, 0]]
            bv = pos[edges[ex, 1]] - B0
            bl = wp.length(bv)
            bh = bv / bl
            q = to_edge2(S3, B0, bh)
            # a window lives in face g: only in faces where unfolding is well conditioned (face_ok)
            if q[1] > 1.0e-7 * bl and use_windows != 0 and face_ok[g] != wp.int8(0):
                nf = g
                a2 = q[0]
                h2 = q[1]
                l2 = lo
                r2 = hi
            else:
                sg = d
        else:
            sg = d
    if nf < 0:
        sg = d
        a2 = 0.0
        h2 = 0.0
    n_in_face[s, x] = nf
    n_info[s, x] = info
    n_wa[s, x] = a2
    n_wh[s, x] = h2
    n_wsig[s, x] = sg
    n_wl[s, x] = l2
    n_wr[s, x] = r2
    n_origin[s, x] = orig


@wp.kernel
def decode_kernel(nv: int, k: int, use_windows: int, pos: wp.array(dtype=wp.vec3), faces: wp.array2d(dtype=int),
                  edges: wp.array2d(dtype=int), face_edges: wp.array2d(dtype=int),
                  edge_faces: wp.array2d(dtype=int), face_ok: wp.array(dtype=wp.int8),
                  key: wp.array2d(dtype=wp.uint64), dist: wp.array2d(dtype=float), in_face: wp.array2d(dtype=int),
                  wa: wp.array2d(dtype=float), wh: wp.array2d(dtype=float), wsig: wp.array2d(dtype=float),
                  wl: wp.array2d(dtype=float), wr: wp.array2d(dtype=float),
                  improved: wp.array2d(dtype=wp.int8), n_in_face: wp.array2d(dtype=int), n_info: wp.array2d(dtype=int),
                  n_wa: wp.array2d(dtype=float), n_wh: wp.array2d(dtype=float), n_wsig: wp.array2d(dtype=float),
                  n_wl: wp.array2d(dtype=float), n_wr: wp.array2d(dtype=float),
                  n_origin: wp.array2d(dtype=int), origin: wp.array2d(dtype=int), pa: wp.array2d(dtype=float),
                  ph: wp.array2d(dtype=float)):
    s, x = wp.tid()
    decode_one(s, x, nv, k, use_windows, pos, faces, edges, face_edges, edge_faces, face_ok, key, dist,
               in_face, wa, wh, wsig, wl, wr, improved, n_in_face, n_info, n_wa, n_wh, n_wsig, n_wl, n_wr,
               n_origin, origin, pa, ph)


@wp.func
def commit_one(s: int, x: int, key: wp.array2d(dtype=wp.uint64), dist: wp.array2d(dtype=float),
               parent: wp.array2d(dtype=int), in_face: wp.array2d(dtype=int), info: wp.array2d(dtype=int),
               wa: wp.array2d(dtype=float), wh: wp.array2d(dtype=float), wsig: wp.array2d(dtype=float),
               wl: wp.array2d(dtype=float), wr: wp.array2d(dtype=float),
               n_in_face: wp.array2d(dtype=int), n_info: wp.array2d(dtype=int),
               n_wa: wp.array2d(dtype=float), n_wh: wp.array2d(dtype=float), n_wsig: wp.array2d(dtype=float),
               n_wl: wp.array2d(dtype=float), n_wr: wp.array2d(dtype=float),
               n_origin: wp.array2d(dtype=int), origin: wp.array2d(dtype=int)) -> float:
    kk = key[s, x]
    d = unpack_dist(kk)
    dist[s, x] = d
    parent[s, x] = unpack_parent(kk)
    in_face[s, x] = n_in_face[s, x]
    info[s, x] = n_info[s, x]
    wa[s, x] = n_wa[s, x]
    wh[s, x] = n_wh[s, x]
    wsig[s, x] = n_wsig[s, x]
    wl[s, x] = n_wl[s, x]
    wr[s, x] = n_wr[s, x]
    origin[s, x] = n_origin[s, x]
    return d


@wp.kernel
def commit_kernel(key: wp.array2d(dtype=wp.uint64), dist: wp.array2d(dtype=float), parent: wp.array2d(dtype=int),
                  in_face: wp.array2d(dtype=int), info: wp.array2d(dtype=int),
                  wa: wp.array2d(dtype=float), wh: wp.array2d(dtype=float), wsig: wp.array2d(dtype=float),
                  wl: wp.array2d(dtype=float), wr: wp.array2d(dtype=float),
                  improved: wp.array2d(dtype=wp.int8), n_in_face: wp.array2d(dtype=int), n_info: wp.array2d(dtype=int),
                  n_wa: wp.array2d(dtype=float), n_wh: wp.array2d(dtype=float), n_wsig: wp.array2d(dtype=float),
                  n_wl: wp.array2d(dtype=float), n_wr: wp.array2d(dtype=float),
                  n_origin: wp.array2d(dtype=int), origin: wp.array2d(dtype=int),
                  changed: wp.array2d(dtype=wp.int8), cond: wp.array(dtype=int), counter: wp.array(dtype=int),
                  max_iter: int, thr: wp.array(dtype=float), minpend: wp.array(dtype=float)):
    s, x = wp.tid()
    if improved[s, x] == wp.int8(0):
        # still pending if it changed but was beyond this iteration's threshold
        if changed[s, x] != wp.int8(0):
            dx = dist[s, x]
            if dx < thr[s]:
                changed[s, x] = wp.int8(0)
            else:
                wp.atomic_min(minpend, s, dx)
                if counter[0] < max_iter:
                    cond[0] = 1
        return
    d = commit_one(s, x, key, dist, parent, in_face, info, wa, wh, wsig, wl, wr, n_in_face, n_info, n_wa, n_wh,
                   n_wsig, n_wl, n_wr, n_origin, origin)
    changed[s, x] = wp.int8(1)
    wp.atomic_min(minpend, s, d)
    if counter[0] < max_iter:
        cond[0] = 1


@wp.kernel
def gather_kernel(dist: wp.array2d(dtype=float), nv: int, scale: float, out: wp.array2d(dtype=float)):
    s, v = wp.tid()
    out[s, v] = dist[s, v] * scale


@wp.func
def unfold_source(u: int, g: int, s: int, nv: int, k: int, pos: wp.array(dtype=wp.vec3), faces: wp.array2d(dtype=int),
                  edges: wp.array2d(dtype=int), wa: wp.array2d(dtype=float), wh: wp.array2d(dtype=float)) -> wp.vec3:
    e = (u - nv) // k
    A = pos[edges[e, 0]]
    ev = pos[edges[e, 1]] - A
    eh = ev / wp.length(ev)
    ng = in_plane_normal(A, eh, pos[opposite_vertex(g, e, faces, edges)])
    return A + wa[s, u] * eh - wh[s, u] * ng


@wp.kernel
def trace_kernel(nv: int, k: int, pos: wp.array(dtype=wp.vec3), faces: wp.array2d(dtype=int),
                 edges: wp.array2d(dtype=int), row: wp.array(dtype=int), targets: wp.array(dtype=int),
                 parent: wp.array2d(dtype=int), in_face: wp.array2d(dtype=int), info: wp.array2d(dtype=int),
                 wa: wp.array2d(dtype=float), wh: wp.array2d(dtype=float),
                 wl: wp.array2d(dtype=float), wr: wp.array2d(dtype=float),
                 max_steps: int, write: int, offsets: wp.array(dtype=int), pts: wp.array(dtype=wp.vec3),
                 counts: wp.array(dtype=int), stale: wp.array(dtype=int)):
    """Walk a path back from its target to the source (points in target->source order).
    write=0 only counts points; write=1 stores them at offsets[t]."""
    t = wp.tid()
    s = row[t]
    cur = targets[t]
    base = int(0)
    if write != 0:
        base = offsets[t]
    P = pos[cur]
    if write != 0:
        pts[base] = P
    n = int(1)
    at_node = bool(True)
    nstale = int(0)
    done = bool(False)
    if parent[s, cur] < 0:
        counts[t] = 0
        stale[t] = 0
        return
    for step in range(max_steps):
        par = parent[s, cur]
        if not at_node and in_face[s, cur] < 0:
            # we crossed cur's edge away from cur but cur holds no window (stale chain): bend at cur
            P = node_pos(cur, nv, k, pos, edges)
            if write != 0:
                pts[base + n] = P
            n += 1
            at_node = True
            nstale += 1
        if par == cur:
            if not at_node:
                P = node_pos(cur, nv, k, pos, edges)
                if write != 0:
                    pts[base + n] = P
                n += 1
            done = True
            break
        inf = info[s, cur]
        if inf < 0 or (inf % 2) == 0 or in_face[s, par] < 0 or par < nv:
            if inf >= 0 and (inf % 2) == 1:
                nstale += 1
            P = node_pos(par, nv, k, pos, edges)
            if write != 0:
                pts[base + n] = P
            n += 1
            cur = par
            at_node = True
            continue
        g = inf // 2
        S3 = unfold_source(par, g, s, nv, k, pos, faces, edges, wa, wh)
        e = (par - nv) // k
        A = pos[edges[e, 0]]
        ev = pos[edges[e, 1]] - A
        elen = wp.length(ev)
        eh = ev / elen
        q = to_edge2(P, A, eh)
        ua = wa[s, par]
        uh = wh[s, par]
        c = (ua + (q[0] - ua) * uh / (uh + q[1])) / elen
        tol = 1.0e-4
        if c < wl[s, par] - tol or c > wr[s, par] + tol or q[1] <= 0.0:
            nstale += 1
            P = node_pos(par, nv, k, pos, edges)
            at_node = True
        else:
            P = A + wp.clamp(c, 0.0, 1.0) * ev
            at_node = False
        if write != 0:
            pts[base + n] = P
        n += 1
        cur = par
    counts[t] = n
    if not done:
        nstale = -1
    stale[t] = nstale


# ---- frontier worklist version --------------------------------------------------------------------------
# Per source row s: `cur[s, :ccount[s]]` holds the active nodes (improved, not yet relaxed); nodes closer than the
# row's threshold relax (node-centric: the faces around the node), the others are carried to `nxt`. Nodes whose
# key went down are appended once per iteration to `tlist` (tstamp = iteration), decoded and committed from that
# list only; committed nodes join `nxt` unless already carried (qstamp = iteration). Launches are (rows, T) with a
# grid-stride loop over the row's list, so dims are fixed at capture time and the work follows the list sizes.
# work[s, 0..2] counts relaxed nodes, list entries read (cur) and decoded entries (tlist) per row.


@wp.func
def slot_of(g: int, u: int, nv: int, k: int, faces: wp.array2d(dtype=int), face_edges: wp.array2d(dtype=int)) -> int:
    if u < nv:
        if faces[g, 0] == u:
            return 0
        if faces[g, 1] == u:
            return 1
        return 2
    m = u - nv
    e = m // k
    le = int(0)
    if face_edges[g, 1] == e:
        le = 1
    elif face_edges[g, 2] == e:
        le = 2
    return 3 + le * k + (m - e * k)


@wp.kernel
def init_list_kernel(sources: wp.array(dtype=int), cur: wp.array2d(dtype=int), ccount: wp.array(dtype=int),
                     minpend: wp.array(dtype=float)):
    s = wp.tid()
    cur[s, 0] = sources[s]
    ccount[s] = 1
    minpend[s] = 0.0


@wp.kernel
def clear_list_kernel(cond: wp.array(dtype=int), counter: wp.array(dtype=int), thr: wp.array(dtype=float),
                      minpend: wp.array(dtype=float), delta: float, ncount: wp.array(dtype=int),
                      tcount: wp.array(dtype=int)):
    s = wp.tid()
    thr[s] = minpend[s] + delta
    minpend[s] = INF
    ncount[s] = 0
    tcount[s] = 0
    if s == 0:
        counter[0] = counter[0] + 1
        cond[0] = 0


@wp.kernel
def relax_list_kernel(nv: int, k: int, use_windows: int, pos: wp.array(dtype=wp.vec3), faces: wp.array2d(dtype=int),
                      edges: wp.array2d(dtype=int), face_edges: wp.array2d(dtype=int),
                      face_ok: wp.array(dtype=wp.int8),
                      vf_off: wp.array(dtype=int), vf_idx: wp.array(dtype=int),
                      ef_off: wp.array(dtype=int), ef_idx: wp.array(dtype=int),
                      dist: wp.array2d(dtype=float), in_face: wp.array2d(dtype=int),
                      wa: wp.array2d(dtype=float), wh: wp.array2d(dtype=float), wsig: wp.array2d(dtype=float),
                      wl: wp.array2d(dtype=float), wr: wp.array2d(dtype=float),
                      cur: wp.array2d(dtype=int), ccount: wp.array(dtype=int),
                      nxt: wp.array2d(dtype=int), ncount: wp.array(dtype=int), qstamp: wp.array2d(dtype=int),
                      tlist: wp.array2d(dtype=int), tcount: wp.array(dtype=int), tstamp: wp.array2d(dtype=int),
                      thr: wp.array(dtype=float), minpend: wp.array(dtype=float), key: wp.array2d(dtype=wp.uint64),
                      counter: wp.array(dtype=int), cond: wp.array(dtype=int), max_iter: int,
                      work: wp.array2d(dtype=int), nthreads: int):
    s, t = wp.tid()
    it = counter[0]
    n = ccount[s]
    th = thr[s]
    ns = 3 + 3 * k
    nrel = int(0)
    nread = int(0)
    pmin = float(INF)
    i = t
    while i < n:
        u = cur[s, i]
        i += nthreads
        nread += 1
        du = dist[s, u]
        if not (du < th):
            # pending: carry to the next list
            qstamp[s, u] = it
            slot = wp.atomic_add(ncount, s, 1)
            nxt[s, slot] = u
            pmin = wp.min(pmin, du)
            continue
        nrel += 1
        pu = node_pos(u, nv, k, pos, edges)
        f0 = int(0)
        f1 = int(0)
        ue = int(-1)
        if u < nv:
            f0 = vf_off[u]
            f1 = vf_off[u + 1]
        else:
            ue = (u - nv) // k
            f0 = ef_off[ue]
            f1 = ef_off[ue + 1]
        win_ok = bool(False)
        A = wp.vec3()
        eh = wp.vec3()
        elen = float(0.0)
        f_in = int(-1)
        if use_windows != 0 and u >= nv:
            f_in = in_face[s, u]
            if f_in >= 0:
                win_ok = True
                A, eh, elen = edge_frame(ue, pos, edges)
        for fi in range(f0, f1):
            g = int(0)
            if u < nv:
                g = vf_idx[fi]
            else:
                g = ef_idx[fi]
            iu = slot_of(g, u, nv, k, faces, face_edges)
            win = win_ok and f_in != g and face_ok[g] != wp.int8(0)
            for j in range(ns):
                if j == iu:
                    continue
                x, d = face_candidate(s, u, du, pu, iu, j, g, win, A, eh, elen, nv, k, pos, faces, edges,
                                      face_edges, wa, wh, wsig, wl, wr)
                if propose(key, s, x, d, u):
                    # first improvement of x this iteration: append it to the decode list
                    if wp.atomic_max(tstamp, s, x, it) < it:
                        slot = wp.atomic_add(tcount, s, 1)
                        tlist[s, slot] = x
    if pmin < INF:
        wp.atomic_min(minpend, s, pmin)
        if it < max_iter:
            cond[0] = 1
    if nread > 0:
        wp.atomic_add(work, s, 0, nrel)
        wp.atomic_add(work, s, 1, nread)


@wp.kernel
def decode_list_kernel(nv: int, k: int, use_windows: int, pos: wp.array(dtype=wp.vec3), faces: wp.array2d(dtype=int),
                       edges: wp.array2d(dtype=int), face_edges: wp.array2d(dtype=int),
                       edge_faces: wp.array2d(dtype=int), face_ok: wp.array(dtype=wp.int8),
                       key: wp.array2d(dtype=wp.uint64), dist: wp.array2d(dtype=float), in_face: wp.array2d(dtype=int),
                       wa: wp.array2d(dtype=float), wh: wp.array2d(dtype=float), wsig: wp.array2d(dtype=float),
                       wl: wp.array2d(dtype=float), wr: wp.array2d(dtype=float),
                       improved: wp.array2d(dtype=wp.int8), n_in_face: wp.array2d(dtype=int),
                       n_info: wp.array2d(dtype=int),
                       n_wa: wp.array2d(dtype=float), n_wh: wp.array2d(dtype=float), n_wsig: wp.array2d(dtype=float),
                       n_wl: wp.array2d(dtype=float), n_wr: wp.array2d(dtype=float),
                       n_origin: wp.array2d(dtype=int), origin: wp.array2d(dtype=int), pa: wp.array2d(dtype=float),
                       ph: wp.array2d(dtype=float), tlist: wp.array2d(dtype=int), tcount: wp.array(dtype=int),
                       work: wp.array2d(dtype=int), nthreads: int):
    s, t = wp.tid()
    n = tcount[s]
    i = t
    while i < n:
        x = tlist[s, i]
        i += nthreads
        decode_one(s, x, nv, k, use_windows, pos, faces, edges, face_edges, edge_faces, face_ok, key, dist,
                   in_face, wa, wh, wsig, wl, wr, improved, n_in_face, n_info, n_wa, n_wh, n_wsig, n_wl, n_wr,
                   n_origin, origin, pa, ph)
    if t == 0:
        wp.atomic_add(work, s, 2, n)


@wp.kernel
def commit_list_kernel(key: wp.array2d(dtype=wp.uint64), dist: wp.array2d(dtype=float), parent: wp.array2d(dtype=int),
                       in_face: wp.array2d(dtype=int), info: wp.array2d(dtype=int),
                       wa: wp.array2d(dtype=float), wh: wp.array2d(dtype=float), wsig: wp.array2d(dtype=float),
                       wl: wp.array2d(dtype=float), wr: wp.array2d(dtype=float),
                       improved: wp.array2d(dtype=wp.int8), n_in_face: wp.array2d(dtype=int),
                       n_info: wp.array2d(dtype=int),
                       n_wa: wp.array2d(dtype=float), n_wh: wp.array2d(dtype=float), n_wsig: wp.array2d(dtype=float),
                       n_wl: wp.array2d(dtype=float), n_wr: wp.array2d(dtype=float),
                       n_origin: wp.array2d(dtype=int), origin: wp.array2d(dtype=int),
                       tlist: wp.array2d(dtype=int), tcount: wp.array(dtype=int),
                       nxt: wp.array2d(dtype=int), ncount: wp.array(dtype=int), qstamp: wp.array2d(dtype=int),
                       cond: wp.array(dtype=int), counter: wp.array(dtype=int), max_iter: int,
                       minpend: wp.array(dtype=float), nthreads: int):
    s, t = wp.tid()
    it = counter[0]
    n = tcount[s]
    i = t
    dmin = float(INF)
    while i < n:
        x = tlist[s, i]
        i += nthreads
        if improved[s, x] == wp.int8(0):
            continue
        d = commit_one(s, x, key, dist, parent, in_face, info, wa, wh, wsig, wl, wr, n_in_face, n_info, n_wa, n_wh,
                       n_wsig, n_wl, n_wr, n_origin, origin)
        dmin = wp.min(dmin, d)
        if qstamp[s, x] != it:
            qstamp[s, x] = it
            slot = wp.atomic_add(ncount, s, 1)
            nxt[s, slot] = x
    if dmin < INF:
        wp.atomic_min(minpend, s, dmin)
        if it < max_iter:
            cond[0] = 1


# ---- consistent distances and paths from the path records ------------------------------------------------
# Node x's path record: its origin o (the node its straight unfolded ray, or its graph edge, goes back to) and, for a
# ray (info odd), the virtual source (pa, ph) in the frame of its parent's edge, unfolded into face info//2. The
# record never changes after x's last improvement, but o may have improved later (then x's distance is longer than
# o's current distance + the ray). `slack` = d_x - (d_o + ray length) >= 0; pointer jumping sums it along the origin
# chain, and d_x - (sum) is exactly the length of the polyline the tracer walks (the same or shorter: still an
# upper bound of the exact distance).


@wp.func
def record_len(s: int, x: int, nv: int, k: int, pos: wp.array(dtype=wp.vec3), faces: wp.array2d(dtype=int),
               edges: wp.array2d(dtype=int), parent: wp.array2d(dtype=int), info: wp.array2d(dtype=int),
               pa: wp.array2d(dtype=float), ph: wp.array2d(dtype=float)) -> float:
    px = node_pos(x, nv, k, pos, edges)
    par = parent[s, x]
    inf = info[s, x]
    if inf >= 0 and (inf % 2) == 1:
        g = inf // 2
        e = (par - nv) // k
        A = pos[edges[e, 0]]
        ev = pos[edges[e, 1]] - A
        eh = ev / wp.length(ev)
        ng = in_plane_normal(A, eh, pos[opposite_vertex(g, e, faces, edges)])
        S3 = A + pa[s, x] * eh - ph[s, x] * ng
        return wp.length(S3 - px)
    return wp.length(px - node_pos(par, nv, k, pos, edges))


@wp.kernel
def slack_init_kernel(nv: int, k: int, pos: wp.array(dtype=wp.vec3), faces: wp.array2d(dtype=int),
                      edges: wp.array2d(dtype=int), dist: wp.array2d(dtype=float), parent: wp.array2d(dtype=int),
                      info: wp.array2d(dtype=int), origin: wp.array2d(dtype=int), pa: wp.array2d(dtype=float),
                      ph: wp.array2d(dtype=float), ptr: wp.array2d(dtype=int), acc: wp.array2d(dtype=float)):
    s, x = wp.tid()
    par = parent[s, x]
    if par < 0 or par == x or not (dist[s, x] < INF):
        ptr[s, x] = x
        acc[s, x] = 0.0
        return
    o = origin[s, x]
    ptr[s, x] = o
    sl = dist[s, x] - (dist[s, o] + record_len(s, x, nv, k, pos, faces, edges, parent, info, pa, ph))
    acc[s, x] = wp.max(sl, 0.0)


@wp.kernel
def slack_jump_kernel(ptr: wp.array2d(dtype=int), acc: wp.array2d(dtype=float), ptr2: wp.array2d(dtype=int),
                      acc2: wp.array2d(dtype=float)):
    s, x = wp.tid()
    p = ptr[s, x]
    acc2[s, x] = acc[s, x] + acc[s, p]
    ptr2[s, x] = ptr[s, p]


@wp.kernel
def slack_apply_kernel(acc: wp.array2d(dtype=float), dist: wp.array2d(dtype=float)):
    s, x = wp.tid()
    a = acc[s, x]
    if a > 0.0:
        dist[s, x] = dist[s, x] - a


@wp.func
def walk_ray(cur: int, o: int, g: int, S_in: wp.vec3, nv: int, k: int, pos: wp.array(dtype=wp.vec3),
             faces: wp.array2d(dtype=int), edges: wp.array2d(dtype=int), face_edges: wp.array2d(dtype=int),
             edge_faces: wp.array2d(dtype=int), face_ok: wp.array(dtype=wp.int8), max_steps: int, write: int,
             pts: wp.array(dtype=wp.vec3), at: int):
    """Walk the straight unfolded ray from node cur (in face g) towards the virtual source S_in until the face
    holding the origin o. Returns (number of crossing points (written at pts[at...] when write=1), vertex):
    vertex = -1 when the walk reached the origin's face; (n, v) when the walk stopped (circling, no exit, a
    boundary, a graph-only face) with its last crossing point on mesh vertex v (the ray ran through v within
    rounding): the caller ends the ray at v and goes on along v's own path; (-1, -1) when the walk fails."""
    S = S_in
    n = int(0)
    steps = int(0)
    Q = node_pos(cur, nv, k, pos, edges)
    face = g
    # edges the walk must not leave through: those holding the start point, then the entry edge
    ex0 = int(-1)
    ex1 = int(-1)
    if cur >= nv:
        ex0 = (cur - nv) // k
    else:
        for le in range(3):
            if faces[g, le] == cur or faces[g, (le + 1) % 3] == cur:
                if ex0 < 0:
                    ex0 = face_edges[g, le]
                else:
                    ex1 = face_edges[g, le]
    ok = bool(False)
    snap = int(-1)
    while steps < max_steps:
        steps += 1
        if face_has_node(face, o, nv, k, faces, face_edges):
            ok = True  # the origin is on this face: the rest of the ray is the straight segment to it
            break
        p0 = pos[faces[face, 0]]
        nrm = wp.cross(pos[faces[face, 1]] - p0, pos[faces[face, 2]] - p0)
        dv = S - Q
        best_t = float(2.0)
        best_le = int(-1)
        best_w = float(0.0)
        for le in range(3):
            ed = face_edges[face, le]
            if ed == ex0 or ed == ex1:
                continue
            B0 = pos[faces[face, le]]
            evl = pos[faces[face, (le + 1) % 3]] - B0
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
        ed = face_edges[face, best_le]
        B0 = pos[faces[face, best_le]]
        Q = B0 + wp.clamp(best_w, 0.0, 1.0) * (pos[faces[face, (best_le + 1) % 3]] - B0)
        if write != 0:
            pts[at + n] = Q
        n += 1
        f0 = edge_faces[ed, 0]
        nf = edge_faces[ed, 1]
        if f0 != face:
            nf = f0
        if nf < 0 or nf == face or face_ok[nf] == wp.int8(0):
            break  # windows never cross graph-only faces: the walk has strayed (or left through a vertex)
        A2 = pos[edges[ed, 0]]
        ev2 = pos[edges[ed, 1]] - A2
        eh2 = ev2 / wp.length(ev2)
        r = S - A2
        n2 = in_plane_normal(A2, eh2, pos[opposite_vertex(nf, ed, faces, edges)])
        S = A2 + wp.dot(r, eh2) * eh2 + wp.length(wp.cross(r, eh2)) * n2
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
            pv = pos[faces[face, lv]]
            lmax = wp.max(lmax, wp.length(pos[faces[face, (lv + 1) % 3]] - pv))
            dq = wp.length(pv - Q)
            if dq < dbest and faces[face, lv] != cur:
                dbest = dq
                snap = faces[face, lv]
        if n > 0 and snap >= 0 and dbest <= 1.0e-3 * lmax:
            return n, snap
        return int(-1), int(-1)
    return n, int(-1)


@wp.kernel
def walk_kernel(nv: int, k: int, pos: wp.array(dtype=wp.vec3), faces: wp.array2d(dtype=int),
                edges: wp.array2d(dtype=int), face_edges: wp.array2d(dtype=int), edge_faces: wp.array2d(dtype=int),
                face_ok: wp.array(dtype=wp.int8),
                row: wp.array(dtype=int), targets: wp.array(dtype=int), parent: wp.array2d(dtype=int),
                info: wp.array2d(dtype=int), origin: wp.array2d(dtype=int), pa: wp.array2d(dtype=float),
                ph: wp.array2d(dtype=float), max_steps: int, write: int, offsets: wp.array(dtype=int),
                pts: wp.array(dtype=wp.vec3), counts: wp.array(dtype=int), stale: wp.array(dtype=int)):
    """Walk a path back from its target to the source along the path records (target->source order): a graph
    edge goes straight to the parent; a ray walks straight towards its virtual source, face by face (unfolding
    the source across each crossed edge), and ends at the record's origin. write=0 only counts points."""
    t = wp.tid()
    s = row[t]
    cur = targets[t]
    base = int(0)
    if write != 0:
        base = offsets[t]
    if parent[s, cur] < 0:
        counts[t] = 0
        stale[t] = 0
        return
    if write != 0:
        pts[base] = pos[cur]
    n = int(1)
    nstale = int(0)
    done = bool(False)
    steps = int(0)
    while steps < max_steps:
        steps += 1
        par = parent[s, cur]
        if par == cur:
            done = True
            break
        inf = info[s, cur]
        o = origin[s, cur]
        if inf < 0 or (inf % 2) == 0:
            if write != 0:
                pts[base + n] = node_pos(par, nv, k, pos, edges)
            n += 1
            cur = par
            continue
        g = inf // 2
        e = (par - nv) // k
        A = pos[edges[e, 0]]
        ev = pos[edges[e, 1]] - A
        eh = ev / wp.length(ev)
        ng = in_plane_normal(A, eh, pos[opposite_vertex(g, e, faces, edges)])
        S = A + pa[s, cur] * eh - ph[s, cur] * ng
        m, snap = walk_ray(cur, o, g, S, nv, k, pos, faces, edges, face_edges, edge_faces, face_ok, max_steps, 0,
                           pts, 0)
        if m < 0:
            # numerically failed walk: bend at the parent (shares face g with cur) and go on from there
            nstale += 1
            if write != 0:
                pts[base + n] = node_pos(par, nv, k, pos, edges)
            n += 1
            cur = par
            continue
        steps += m
        if write != 0:
            walk_ray(cur, o, g, S, nv, k, pos, faces, edges, face_edges, edge_faces, face_ok, max_steps, 1, pts,
                     base + n)
        n += m
        nxt = o
        if snap >= 0:
            nxt = snap  # the ray ran through vertex snap: go on along its own path
        if write != 0:
            pts[base + n] = node_pos(nxt, nv, k, pos, edges)
        n += 1
        cur = nxt
    counts[t] = n
    if not done:
        nstale = -1
    stale[t] = nstale
