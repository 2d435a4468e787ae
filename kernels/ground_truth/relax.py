"""Relaxation of the Steiner graph with unfolding windows: a frontier worklist, delta-stepping, per source row.

Candidates are proposed with a uint64 atomic_min on (distance bits << 32 | parent node); a decode pass then
re-derives the winner's window and path record from the parent's committed state (so a node's window always
matches its distance), and a commit pass makes them current. Every candidate is the length of a real surface
path, so every distance is an upper bound of the exact geodesic distance.

Per source row s: `active[s, :active_count[s]]` holds the active nodes (improved, not yet relaxed). Nodes closer
than the row's threshold (nearest pending distance + delta) relax, node-centric over the faces around them; the
others are carried to `next`. Near-distance order keeps parents from changing after their children used them
and avoids most of plain Bellman-Ford's repeated improvements. Nodes whose key went down are appended once per
iteration to `touched` (touched_stamp = iteration), decoded and committed from that list only; committed nodes
join `next` unless already carried (queued = iteration). Launches are (rows, threads) with a grid-stride loop
over the row's list, so their dims are fixed at graph-capture time and the work follows the list sizes; the relax
launch has `lanes` threads per list entry. Each row's counters sit on their own 128-byte line (LINE), and the
loop's go flag is set once per row (finish_iteration): every append is an atomic on its row's counter.
"""
import warp as wp

from .graph import (
    INF,
    SteinerGraph,
    common_face,
    edge_frame,
    node_pos,
    slot_code,
    slot_of,
    steiner_edge,
)
from .unfolding import Windows, crossing_param, edge_coords, ray_length, unfold_source, window_interval

wp.set_module_options({"enable_backward": False, "fuse_fp": False})


@wp.struct
class PathRecords:
    """How each node's distance was reached; (S, N) arrays. A record never goes stale: it is written with the
    distance, from the parent's state at that moment."""

    parent: wp.array2d(dtype=int)  # the node the winning candidate came from (itself at the source, -1 unreached)
    origin: wp.array2d(dtype=int)  # where the straight piece ends: the parent, or the window's point source
    ray_face: wp.array2d(dtype=int)  # -1: a graph edge to the parent; else the face the ray crosses last
    ray_along: wp.array2d(dtype=float)  # the ray's virtual source in the parent edge's frame (see Windows)
    ray_height: wp.array2d(dtype=float)


@wp.struct
class NodeState:
    """Committed per (row, node) state."""

    key: wp.array2d(dtype=wp.uint64)  # packed (distance, parent) proposals of this iteration
    dist: wp.array2d(dtype=float)
    win: Windows
    rec: PathRecords


@wp.struct
class Staging:
    """Decoded winners waiting for the commit pass."""

    accept: wp.array2d(dtype=wp.int8)  # 1: the key went below the committed distance
    win: Windows
    origin: wp.array2d(dtype=int)
    ray_face: wp.array2d(dtype=int)


@wp.struct
class Frontier:
    """The worklists of one iteration (two instances swap `active` and `next`)."""

    active: wp.array2d(dtype=int)  # (S, N) nodes to relax
    active_count: wp.array2d(dtype=int)  # (S, LINE): the row's count in column 0 (see LINE)
    next: wp.array2d(dtype=int)  # (S, N) nodes for the next iteration
    next_count: wp.array2d(dtype=int)  # (S, LINE)
    queued: wp.array2d(dtype=int)  # (S, N) iteration in which the node joined `next`
    touched: wp.array2d(dtype=int)  # (S, N) nodes whose key went down in this iteration
    touched_count: wp.array2d(dtype=int)  # (S, LINE)
    touched_stamp: wp.array2d(dtype=int)  # (S, N) iteration in which the node joined `touched`
    threshold: wp.array(dtype=float)  # (S,) nodes closer than this relax
    min_pending: wp.array2d(dtype=int)  # (S, LINE) nearest distance left for later, as float bits (see pending)
    delta: float  # bucket width (normalized units; inf: plain Bellman-Ford)
    iteration: wp.array(dtype=int)  # (1,)
    go: wp.array(dtype=int)  # (1,) 1 while any row has work (the capture_while condition; finish_iteration)
    iteration_limit: wp.array(dtype=int)  # (1,) the loop stops after this iteration (work may remain)
    work: wp.array2d(dtype=int)  # (S, LINE) relaxed nodes, list entries read, decoded entries (columns 0-2)
    threads: int  # list entries a row's launch works on at once (the grid-stride of its loops)
    lanes: int  # threads per entry in relax_frontier: they share a node's candidates (faces x slots)


LINE = 32  # ints per row of the per-row counters: each row's counter on its own 128-byte line. Every append to a
# row's list is an atomic on its counter; with the rows' counters side by side in one line, the appends of all rows
# of an iteration queue at one L2 slice.
INF_BITS = wp.constant(wp.int32(0x7F800000))  # float bits of +inf: min_pending when nothing is pending


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
def propose(key: wp.array2d(dtype=wp.uint64), s: int, x: int, d: float, u: int) -> bool:
    """Offer node x distance d through parent u (packed atomic_min); True when this lowered x's key."""
    if d < unpack_dist(key[s, x]):
        pk = pack(d, u)
        old = wp.atomic_min(key, s, x, pk)
        return pk < old
    return False


@wp.func
def pending(front: Frontier, s: int, d: float):
    """Row s has a node left at distance d (inf: none): record the nearest. Distances are >= 0, whose float
    bits order as ints do, so this is one hardware atomic (Warp's float atomic_min is a compare-and-swap loop, and
    every thread of the row meets at this address)."""
    if d < INF:
        bits = int(0)
        if d > 0.0:
            bits = wp.cast(d, int)
        wp.atomic_min(front.min_pending, s, 0, bits)


@wp.kernel
def init_rows(sources: wp.array(dtype=int), state: NodeState):
    """Every node unreached, the row's source at distance 0."""
    s, n = wp.tid()
    src = sources[s]
    state.rec.origin[s, n] = n
    if n == src:
        state.key[s, n] = pack(0.0, n)
        state.dist[s, n] = 0.0
        state.rec.parent[s, n] = n
    else:
        state.key[s, n] = pack(INF, -1)
        state.dist[s, n] = INF
        state.rec.parent[s, n] = -1
    state.win.face[s, n] = -1
    state.rec.ray_face[s, n] = -1


@wp.kernel
def init_frontier(sources: wp.array(dtype=int), front: Frontier):
    s = wp.tid()
    front.active[s, 0] = sources[s]
    front.active_count[s, 0] = 1
    front.min_pending[s, 0] = 0


@wp.kernel
def add_seeds(seeds: wp.array(dtype=int), state: NodeState, front: Frontier):
    """More sources for row 0 (after init_rows / init_frontier seeded it with seeds[0]): every seed at distance 0
    and in the row's active list. A row with one seed per component of a mesh solves them all at once."""
    i = wp.tid()
    n = seeds[i]
    state.key[0, n] = pack(0.0, n)
    state.dist[0, n] = 0.0
    state.rec.parent[0, n] = n
    front.active[0, i] = n
    if i == 0:
        front.active_count[0, 0] = seeds.shape[0]


@wp.kernel
def start_iteration(front: Frontier):
    """Per row: the threshold of this iteration; empty `next` and `touched` lists."""
    s = wp.tid()
    front.threshold[s] = wp.cast(front.min_pending[s, 0], float) + front.delta
    front.min_pending[s, 0] = INF_BITS
    front.next_count[s, 0] = 0
    front.touched_count[s, 0] = 0
    if s == 0:
        front.iteration[0] = front.iteration[0] + 1
        front.go[0] = 0


@wp.kernel
def finish_iteration(front: Frontier):
    """Per row: go on while something is pending, unless at the iteration limit (one store per row, where
    storing from every thread with pending work made them all queue at one address)."""
    s = wp.tid()
    if front.min_pending[s, 0] < INF_BITS and front.iteration[0] < front.iteration_limit[0]:
        front.go[0] = 1


# 96 registers gave 25% occupancy for a kernel that waits on loads; 64 measured fastest (H200, 436K: 17.2 -> 20.9
# sources/s; 80: 18.6, 48 with decode capped too: 19.5; 2026-11-27). The CPU ignores it.
@wp.kernel(cuda_max_registers=64)
def relax_frontier(graph: SteinerGraph, state: NodeState, front: Frontier):
    """Relax the active nodes under the threshold over the faces around them; carry the others.

    `lanes` threads work on each list entry: lane l proposes the node's candidates c = l, l + lanes, ... in
    (face, slot) order. A thread's candidates are a chain of dependent loads and atomics, so the iteration's
    time follows the longest chain (a vertex with many faces, or faces with many Steiner points on thin edges),
    not the number of nodes; the lanes shorten it. Proposals are an atomic min, so the result does not depend
    on which thread makes them."""
    s, t = wp.tid()
    it = front.iteration[0]
    n = front.active_count[s, 0]
    th = front.threshold[s]
    L = front.lanes
    lane = t % L
    nrel = int(0)
    nread = int(0)
    pmin = float(INF)
    i = t // L
    while i < n:
        u = front.active[s, i]
        i += front.threads
        du = state.dist[s, u]
        if lane == 0:
            nread += 1
        if not (du < th):
            # pending: carry to the next list (once, by lane 0)
            if lane == 0:
                front.queued[s, u] = it
                slot = wp.atomic_add(front.next_count, s, 0, 1)
                front.next[s, slot] = u
                pmin = wp.min(pmin, du)
            continue
        if lane == 0:
            nrel += 1
        pu = node_pos(graph, u)
        f0 = int(0)
        f1 = int(0)
        ue = int(-1)
        if u < graph.nv:
            f0 = graph.vertex_face_start[u]
            f1 = graph.vertex_face_start[u + 1]
        else:
            ue = steiner_edge(graph, u)
            f0 = graph.edge_face_start[ue]
            f1 = graph.edge_face_start[ue + 1]
        has_window = bool(False)
        A = wp.vec3()
        eh = wp.vec3()
        elen = float(0.0)
        lo = float(0.0)
        hi = float(0.0)
        wa = float(0.0)
        wh = float(0.0)
        wsg = float(0.0)
        f_in = int(-1)
        if graph.windows != 0 and u >= graph.nv:
            f_in = state.win.face[s, u]
            if f_in >= 0:
                has_window = True
                A, eh, elen = edge_frame(graph, ue)
                lo, hi = window_interval(graph, state.win, s, u, elen)
                wa = state.win.along[s, u]
                wh = state.win.height[s, u]
                wsg = state.win.sigma[s, u]
        c = int(0)  # candidates of the faces before this one
        for fi in range(f0, f1):
            face = int(0)
            if u < graph.nv:
                face = graph.vertex_faces[fi]
            else:
                face = graph.edge_face_list[fi]
            base = graph.face_slot_start[face]
            ns = graph.face_slot_start[face + 1] - base
            j = (lane + L - c % L) % L  # this lane's first slot of the face
            c += ns
            if j < ns:
                iu = slot_of(graph, face, u)
                _un, ubits = slot_code(graph, base, iu)
                through = has_window and f_in != face and graph.window_face[face] != wp.int8(0)
                while j < ns:
                    if j != iu:
                        # candidate: the graph edge u-x, or u's window's straight ray when shorter (through: the
                        # window continues into this face; not along an edge that u lies on)
                        x, xbits = slot_code(graph, base, j)
                        px = node_pos(graph, x)
                        d = du + wp.length(px - pu)
                        if through and (ubits & xbits) == 0:
                            dw = ray_length(wa, wh, wsg, lo, hi, A, eh, elen, px)
                            if dw < d:
                                d = dw
                        if propose(state.key, s, x, d, u):
                            # first improvement of x this iteration: append it to the decode list
                            if wp.atomic_max(front.touched_stamp, s, x, it) < it:
                                slot = wp.atomic_add(front.touched_count, s, 0, 1)
                                front.touched[s, slot] = x
                    j += L
    pending(front, s, pmin)
    if nread > 0:
        wp.atomic_add(front.work, s, 0, nrel)
        wp.atomic_add(front.work, s, 1, nread)


@wp.func
def decode_node(graph: SteinerGraph, state: NodeState, staged: Staging, s: int, x: int):
    """Decode node x's winning proposal: its new window and the origin and ray face of its path record (staged)
    and, when x was reached through its parent's window, that window's virtual source (written directly to
    the records: only the tracer reads them)."""
    kk = state.key[s, x]
    d = unpack_dist(kk)
    if not (d < state.dist[s, x]):
        staged.accept[s, x] = wp.int8(0)
        return
    staged.accept[s, x] = wp.int8(1)
    u = unpack_parent(kk)
    orig = u
    g = common_face(graph, u, x)
    # default: x is a point source of its own (always valid: a real path of length d reaches x)
    nf = int(-1)
    a2 = float(0.0)
    h2 = float(0.0)
    sg = d
    l2 = float(0.0)
    r2 = float(1.0)
    ray_face = int(-1)
    if g >= 0:
        px = node_pos(graph, x)
        pu = node_pos(graph, u)
        via = bool(False)
        source = pu  # the point the straight piece to x starts from (unfolded into face g)
        sg = state.dist[s, u]
        lo = float(0.0)
        hi = float(1.0)
        if graph.windows != 0 and u >= graph.nv and graph.window_face[g] != wp.int8(0):
            f_in = state.win.face[s, u]
            if f_in >= 0 and f_in != g:
                e = steiner_edge(graph, u)
                A, eh, elen = edge_frame(graph, e)
                ua = state.win.along[s, u]
                uh = state.win.height[s, u]
                ulo, uhi = window_interval(graph, state.win, s, u, elen)
                dw = ray_length(ua, uh, state.win.sigma[s, u], ulo, uhi, A, eh, elen, px)
                if dw < sg + wp.length(px - pu):
                    via = True
                    sg = state.win.sigma[s, u]
                    source = unfold_source(graph, e, g, ua, uh)
                    if x >= graph.nv:
                        ex = steiner_edge(graph, x)
                        P0 = edge_coords(graph.pos[graph.edges[ex, 0]], A, eh)
                        P1 = edge_coords(graph.pos[graph.edges[ex, 1]], A, eh)
                        c_start = (ua + (P0[0] - ua) * uh / (uh + P0[1])) / elen
                        c_end = (ua + (P1[0] - ua) * uh / (uh + P1[1])) / elen
                        source_2d = wp.vec2(ua, -uh)
                        t0 = crossing_param(ulo, c_start, c_end, source_2d, elen, P0, P1)
                        t1 = crossing_param(uhi, c_start, c_end, source_2d, elen, P0, P1)
                        lo = wp.min(t0, t1)
                        hi = wp.max(t0, t1)
        if via:
            ray_face = g
            orig = state.rec.origin[s, u]
            state.rec.ray_along[s, x] = state.win.along[s, u]
            state.rec.ray_height[s, x] = state.win.height[s, u]
        if x >= graph.nv:
            B0, bh, bl = edge_frame(graph, steiner_edge(graph, x))
            q = edge_coords(source, B0, bh)
            # a window lives in face g: only in faces where unfolding is well conditioned (window_face)
            if q[1] > 1.0e-7 * bl and graph.windows != 0 and graph.window_face[g] != wp.int8(0):
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
    staged.win.face[s, x] = nf
    staged.win.along[s, x] = a2
    staged.win.height[s, x] = h2
    staged.win.sigma[s, x] = sg
    staged.win.lo[s, x] = l2
    staged.win.hi[s, x] = r2
    staged.ray_face[s, x] = ray_face
    staged.origin[s, x] = orig


@wp.kernel
def decode_touched(graph: SteinerGraph, state: NodeState, staged: Staging, front: Frontier):
    s, t = wp.tid()
    n = front.touched_count[s, 0]
    i = t
    while i < n:
        x = front.touched[s, i]
        i += front.threads
        decode_node(graph, state, staged, s, x)
    if t == 0:
        wp.atomic_add(front.work, s, 2, n)


@wp.func
def copy_window(src: Windows, dst: Windows, s: int, x: int):
    dst.face[s, x] = src.face[s, x]
    dst.along[s, x] = src.along[s, x]
    dst.height[s, x] = src.height[s, x]
    dst.sigma[s, x] = src.sigma[s, x]
    dst.lo[s, x] = src.lo[s, x]
    dst.hi[s, x] = src.hi[s, x]


@wp.kernel
def commit_touched(state: NodeState, staged: Staging, front: Frontier):
    """Make the decoded winners current and queue them for the next iteration."""
    s, t = wp.tid()
    it = front.iteration[0]
    n = front.touched_count[s, 0]
    i = t
    dmin = float(INF)
    while i < n:
        x = front.touched[s, i]
        i += front.threads
        if staged.accept[s, x] == wp.int8(0):
            continue
        kk = state.key[s, x]
        d = unpack_dist(kk)
        state.dist[s, x] = d
        state.rec.parent[s, x] = unpack_parent(kk)
        copy_window(staged.win, state.win, s, x)
        state.rec.ray_face[s, x] = staged.ray_face[s, x]
        state.rec.origin[s, x] = staged.origin[s, x]
        dmin = wp.min(dmin, d)
        if front.queued[s, x] != it:
            front.queued[s, x] = it
            slot = wp.atomic_add(front.next_count, s, 0, 1)
            front.next[s, slot] = x
    pending(front, s, dmin)
