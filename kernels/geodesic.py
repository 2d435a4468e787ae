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


@wp.kernel
def init_kernel(sources: wp.array(dtype=int), key: wp.array2d(dtype=wp.uint64), dist: wp.array2d(dtype=float),
                parent: wp.array2d(dtype=int), in_face: wp.array2d(dtype=int), info: wp.array2d(dtype=int),
                changed: wp.array2d(dtype=wp.int8)):
    s, n = wp.tid()
    src = sources[s]
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
                e = (u - nv) // k
                A = pos[edges[e, 0]]
                ev = pos[edges[e, 1]] - A
                elen = wp.length(ev)
                eh = ev / elen
        for j in range(ns):
            if j == i:
                continue
            x = slot_node(g, j, nv, k, faces, face_edges)
            px = node_pos(x, nv, k, pos, edges)
            d = du + wp.length(px - pu)
            if win and not slots_share_edge(i, j, k):
                dw = window_dist(wa[s, u], wh[s, u], wsig[s, u], wl[s, u], wr[s, u], A, eh, elen, px)
                if dw < d:
                    d = dw
            if d < unpack_dist(key[s, x]):
                wp.atomic_min(key, s, x, pack(d, u))


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


@wp.kernel
def decode_kernel(nv: int, k: int, use_windows: int, pos: wp.array(dtype=wp.vec3), faces: wp.array2d(dtype=int),
                  edges: wp.array2d(dtype=int), face_edges: wp.array2d(dtype=int),
                  edge_faces: wp.array2d(dtype=int), face_ok: wp.array(dtype=wp.int8),
                  key: wp.array2d(dtype=wp.uint64), dist: wp.array2d(dtype=float), in_face: wp.array2d(dtype=int),
                  wa: wp.array2d(dtype=float), wh: wp.array2d(dtype=float), wsig: wp.array2d(dtype=float),
                  wl: wp.array2d(dtype=float), wr: wp.array2d(dtype=float),
                  improved: wp.array2d(dtype=wp.int8), n_in_face: wp.array2d(dtype=int), n_info: wp.array2d(dtype=int),
                  n_wa: wp.array2d(dtype=float), n_wh: wp.array2d(dtype=float), n_wsig: wp.array2d(dtype=float),
                  n_wl: wp.array2d(dtype=float), n_wr: wp.array2d(dtype=float)):
    s, x = wp.tid()
    kk = key[s, x]
    d = unpack_dist(kk)
    if not (d < dist[s, x]):
        improved[s, x] = wp.int8(0)
        return
    improved[s, x] = wp.int8(1)
    u = unpack_parent(kk)
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
        if x >= nv:
            ex = (x - nv) // k
            B0 = pos[edges[ex, 0]]
            bv = pos[edges[ex, 1]] - B0
            bl = wp.length(bv)
            bh = bv / bl
            q = to_edge2(S3, B0, bh)
            if q[1] > 1.0e-7 * bl:
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


@wp.kernel
def commit_kernel(key: wp.array2d(dtype=wp.uint64), dist: wp.array2d(dtype=float), parent: wp.array2d(dtype=int),
                  in_face: wp.array2d(dtype=int), info: wp.array2d(dtype=int),
                  wa: wp.array2d(dtype=float), wh: wp.array2d(dtype=float), wsig: wp.array2d(dtype=float),
                  wl: wp.array2d(dtype=float), wr: wp.array2d(dtype=float),
                  improved: wp.array2d(dtype=wp.int8), n_in_face: wp.array2d(dtype=int), n_info: wp.array2d(dtype=int),
                  n_wa: wp.array2d(dtype=float), n_wh: wp.array2d(dtype=float), n_wsig: wp.array2d(dtype=float),
                  n_wl: wp.array2d(dtype=float), n_wr: wp.array2d(dtype=float),
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
    kk = key[s, x]
    dist[s, x] = unpack_dist(kk)
    parent[s, x] = unpack_parent(kk)
    in_face[s, x] = n_in_face[s, x]
    info[s, x] = n_info[s, x]
    wa[s, x] = n_wa[s, x]
    wh[s, x] = n_wh[s, x]
    wsig[s, x] = n_wsig[s, x]
    wl[s, x] = n_wl[s, x]
    wr[s, x] = n_wr[s, x]
    changed[s, x] = wp.int8(1)
    wp.atomic_min(minpend, s, unpack_dist(kk))
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
