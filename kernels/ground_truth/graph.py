"""The Steiner graph on a triangle mesh as the solver's kernels see it: node ids, positions, face slots, edge frames.

Nodes: the V mesh vertices, then the Steiner points of each unique edge e: count(e) = edge_node_start[e + 1] -
edge_node_start[e] points (k on a well-shaped mesh, more on edges much longer than their faces are wide: see
steiner_graph.steiner_counts), node V + edge_node_start[e] + j at t = (j+1)/(count(e)+1) from the edge's lower
vertex to its higher one. The graph's edges are never stored: all boundary nodes of a face are joined to each
other, so relaxing face by face visits every graph edge. A face's boundary nodes are its "slots": 0..2 its
vertices, then the Steiner points of its local edges 0, 1, 2 in turn (local edge le joins its vertices le and
(le + 1) % 3), listed per face in `face_slot` (steiner_graph.face_slot_table); every node's position is in
`node_xyz`.
"""
import warp as wp

wp.set_module_options({"enable_backward": False, "fuse_fp": False})

INF = wp.constant(float("inf"))


@wp.struct
class SteinerGraph:
    """The mesh tables of one solver (all int32 ids; positions in the normalized frame)."""

    nv: int  # mesh vertices: node ids 0..nv-1
    k: int  # Steiner points per edge on well-shaped faces (the fewest on any edge)
    kmax: int  # the most Steiner points on any edge
    windows: int  # 1: unfolding windows on; 0: the plain Steiner graph
    pos: wp.array(dtype=wp.vec3)  # (V,) vertex positions
    faces: wp.array2d(dtype=int)  # (F, 3)
    edges: wp.array2d(dtype=int)  # (E, 2) unique edges, lower vertex id first
    face_edges: wp.array2d(dtype=int)  # (F, 3) edge of each local edge
    window_face: wp.array(dtype=wp.int8)  # (F,) 1 where windows may cross the face, 0 graph-only
    vertex_face_start: wp.array(dtype=int)  # (V + 1,) CSR offsets into vertex_faces
    vertex_faces: wp.array(dtype=int)  # faces around each vertex
    edge_face_start: wp.array(dtype=int)  # (E + 1,) CSR offsets into edge_face_list
    edge_face_list: wp.array(dtype=int)  # all faces of each edge (three or more on a non-manifold edge)
    edge_node_start: wp.array(dtype=int)  # (E + 1,) Steiner node offsets (from nv) of each edge
    node_edge: wp.array(dtype=int)  # (N - V,) the edge of each Steiner node
    node_t: wp.array(dtype=float)  # (N - V,) its parameter along the edge from the lower vertex
    node_xyz: wp.array(dtype=wp.vec3)  # (N,) every node's position (node_pos), one load where the formula is five
    face_slot_start: wp.array(dtype=int)  # (F + 1,) CSR offsets into face_slot
    face_slot: wp.array(dtype=int)  # every face's slots in slot order, coded node << 3 | local edges (slot_code)


@wp.func
def steiner_edge(graph: SteinerGraph, n: int) -> int:
    """The edge a Steiner node lies on (n >= nv)."""
    return graph.node_edge[n - graph.nv]


@wp.func
def edge_count(graph: SteinerGraph, e: int) -> int:
    """Steiner points on edge e."""
    return graph.edge_node_start[e + 1] - graph.edge_node_start[e]


@wp.func
def node_pos(graph: SteinerGraph, n: int) -> wp.vec3:
    """Node n's position: a vertex's, or a Steiner point's a + t (b - a) on its edge (a: the lower vertex), in
    float32 as the table was made (steiner_graph.node_positions)."""
    return graph.node_xyz[n]


@wp.func
def slot_code(graph: SteinerGraph, base: int, i: int):
    """Slot i of the face whose slots start at `base` (face_slot_start[face]): (node, local-edge bits; bit le set
    when the slot lies on local edge le: a vertex slot i on i and (i + 2) % 3)."""
    code = graph.face_slot[base + i]
    return code >> 3, code & 7


@wp.func
def slot_of(graph: SteinerGraph, face: int, n: int) -> int:
    """The slot of node n in a face that holds it."""
    if n < graph.nv:
        if graph.faces[face, 0] == n:
            return 0
        if graph.faces[face, 1] == n:
            return 1
        return 2
    m = n - graph.nv
    e = graph.node_edge[m]
    off = int(3)
    for le in range(3):
        fe = graph.face_edges[face, le]
        if fe == e:
            return off + m - graph.edge_node_start[e]
        off += edge_count(graph, fe)
    return -1


@wp.func
def face_has_node(graph: SteinerGraph, face: int, n: int) -> bool:
    if n < graph.nv:
        return graph.faces[face, 0] == n or graph.faces[face, 1] == n or graph.faces[face, 2] == n
    e = steiner_edge(graph, n)
    return graph.face_edges[face, 0] == e or graph.face_edges[face, 1] == e or graph.face_edges[face, 2] == e


@wp.func
def common_face(graph: SteinerGraph, u: int, x: int) -> int:
    """The face holding nodes u and x: >= 0, -2 when they lie on one edge (or are both vertices), -1 if none.
    All faces of the edge are searched (three or more on a non-manifold edge). When several faces hold both
    (duplicated faces: the same three vertices twice) the first is returned: the copies coincide, so the straight
    segment u-x and its unfolding are the same in each."""
    e = -1
    other = u
    if x >= graph.nv:
        e = steiner_edge(graph, x)
    elif u >= graph.nv:
        e = steiner_edge(graph, u)
        other = x
    else:
        return -2
    if other >= graph.nv:
        if steiner_edge(graph, other) == e:
            return -2
    elif graph.edges[e, 0] == other or graph.edges[e, 1] == other:
        return -2
    for i in range(graph.edge_face_start[e], graph.edge_face_start[e + 1]):
        f = graph.edge_face_list[i]
        if face_has_node(graph, f, other):
            return f
    return -1


@wp.func
def other_face(graph: SteinerGraph, e: int, face: int, choice: int) -> int:
    """A face of edge e other than `face`: the only one on a manifold edge (-1 on a boundary edge), the
    `choice`-th (mod their number) on a non-manifold edge."""
    start = graph.edge_face_start[e]
    count = graph.edge_face_start[e + 1] - start
    pick = choice % wp.max(count - 1, 1)
    for i in range(start, start + count):
        f = graph.edge_face_list[i]
        if f != face:
            if pick == 0:
                return f
            pick -= 1
    return -1


@wp.func
def opposite_vertex(graph: SteinerGraph, face: int, e: int) -> int:
    """The vertex of a face that is not on its edge e."""
    a = graph.edges[e, 0]
    b = graph.edges[e, 1]
    c = graph.faces[face, 0]
    if c == a or c == b:
        c = graph.faces[face, 1]
        if c == a or c == b:
            c = graph.faces[face, 2]
    return c


@wp.func
def edge_frame(graph: SteinerGraph, e: int):
    """Frame of edge e: its lower vertex A, unit direction eh and length elen."""
    A = graph.pos[graph.edges[e, 0]]
    ev = graph.pos[graph.edges[e, 1]] - A
    elen = wp.length(ev)
    return A, ev / elen, elen


@wp.func
def position64(graph: SteinerGraph, v: int) -> wp.vec3d:
    return wp.vec3d(graph.pos[v])


@wp.func
def face_normal_in_plane64(graph: SteinerGraph, e: int, face: int) -> wp.vec3d:
    """Unit vector in the plane of a face holding edge e, normal to the edge and pointing to the face's third
    vertex. Computed in float64 from the float32 positions: for a thin face (the third vertex close to the edge's
    line) the float32 difference would lose the direction, while the positions themselves define it exactly."""
    A = position64(graph, graph.edges[e, 0])
    ev = position64(graph, graph.edges[e, 1]) - A
    eh = ev / wp.length(ev)
    w = position64(graph, opposite_vertex(graph, face, e)) - A
    n = w - wp.dot(w, eh) * eh
    ln = wp.length(n)
    if ln <= wp.float64(0.0):
        return wp.vec3d(wp.float64(0.0), wp.float64(0.0), wp.float64(0.0))
    return n / ln


@wp.func
def face_normal_in_plane(graph: SteinerGraph, e: int, face: int) -> wp.vec3:
    return wp.vec3(face_normal_in_plane64(graph, e, face))
