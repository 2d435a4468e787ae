"""The solver's per-node and per-slot tables built on its device: one thread per edge or per face.

These tables are the largest of the Steiner graph (about 3k entries per edge and 3 + 3k per face); written on the
device from the small per-edge tables they need no host pass and no upload. Each value is the one the numpy
reference in ground_truth/steiner_graph.py gives, bit for bit: integer codes, and float32 positions from IEEE
operations in the same order (this module is built with fuse_fp off, as the numpy table has no fused
multiply-add).
"""
import warp as wp

wp.set_module_options({"enable_backward": False, "fuse_fp": False})

SLOT_EDGE_BITS = wp.constant(3)  # as steiner_graph.SLOT_EDGE_BITS


@wp.kernel
def steiner_nodes(edges: wp.array2d(dtype=int), edge_node_start: wp.array(dtype=int), pos: wp.array(dtype=wp.vec3),
                  nv: int, node_edge: wp.array(dtype=int), node_t: wp.array(dtype=float),
                  node_xyz: wp.array(dtype=wp.vec3)):
    """Edge e's Steiner points: their edge, their parameter t = (j + 1) / (count + 1) from the lower vertex (in
    float64, rounded to float32) and their position a + t (b - a) (float32, one rounding per operation)."""
    e = wp.tid()
    s = edge_node_start[e]
    c = edge_node_start[e + 1] - s
    a = pos[edges[e, 0]]
    d = pos[edges[e, 1]] - a
    for j in range(c):
        t = wp.float32(wp.float64(j + 1) / wp.float64(c + 1))
        node_edge[s + j] = e
        node_t[s + j] = t
        node_xyz[nv + s + j] = a + t * d


@wp.kernel
def copy_vertices(pos: wp.array(dtype=wp.vec3), node_xyz: wp.array(dtype=wp.vec3)):
    """The first V nodes are the vertices."""
    v = wp.tid()
    node_xyz[v] = pos[v]


@wp.kernel
def face_slots(faces: wp.array2d(dtype=int), face_edges: wp.array2d(dtype=int), edge_node_start: wp.array(dtype=int),
               slot_start: wp.array(dtype=int), nv: int, codes: wp.array(dtype=int)):
    """Face f's slot codes (steiner_graph.face_slot_table): its 3 vertices, on local edges i and (i + 2) % 3, then
    the Steiner points of its local edges 0, 1, 2 in turn, each on its own local edge."""
    f = wp.tid()
    off = slot_start[f]
    for i in range(3):
        codes[off + i] = (faces[f, i] << SLOT_EDGE_BITS) | (1 << i) | (1 << ((i + 2) % 3))
    off += 3
    for le in range(3):
        e = face_edges[f, le]
        s = edge_node_start[e]
        c = edge_node_start[e + 1] - s
        for j in range(c):
            codes[off + j] = ((nv + s + j) << SLOT_EDGE_BITS) | (1 << le)
        off += c


@wp.kernel
def gather_rows(dist: wp.array2d(dtype=float), solver_id: wp.array(dtype=int), out: wp.array2d(dtype=float)):
    """out[r, i] = dist[r, solver_id[i]]: rows of node distances as mesh-vertex rows in the mesh's numbering (on
    the device, so only those V values per row are copied to the host, not the N of every node)."""
    r, i = wp.tid()
    out[r, i] = dist[r, solver_id[i]]
