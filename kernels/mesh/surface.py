"""Closest points on a triangle mesh (``wp.Mesh``): position, face and barycentric coordinates per query.

One thread per query point, ``wp.mesh_query_point_no_sign`` (BVH search, no inside/outside test, so the mesh
need not be closed or consistently oriented). Warp reports the closest point as (face, u, v) with
position = u * v0 + v * v1 + (1 - u - v) * v2 for the face's corners (v0, v1, v2); we return (u, v, 1 - u - v).
"""
import warp as wp


@wp.func
def closest_point(mesh: wp.uint64, x: wp.vec3, max_dist: float):
    """(closest point, face index, barycentric weights of the face's three corners) of x on the mesh;
    face -1 and x itself when no face lies within max_dist. Callable from user kernels."""
    q = wp.mesh_query_point_no_sign(mesh, x, max_dist)
    if not q.result:
        return x, -1, wp.vec3(0.0, 0.0, 0.0)
    return wp.mesh_eval_position(mesh, q.face, q.u, q.v), q.face, wp.vec3(q.u, q.v, 1.0 - q.u - q.v)


@wp.kernel(enable_backward=False)
def snap_points(mesh: wp.uint64, xs: wp.array(dtype=wp.vec3), max_dist: float, points: wp.array(dtype=wp.vec3),
                face: wp.array(dtype=wp.int32), bary: wp.array(dtype=wp.vec3)):
    i = wp.tid()
    x = xs[i]
    if not (wp.isfinite(x[0]) and wp.isfinite(x[1]) and wp.isfinite(x[2])):
        # a NaN row of a path (across components, or a point refused with check=False) stays NaN, on no face
        nan = wp.nan
        points[i] = wp.vec3(nan, nan, nan)
        face[i] = -1
        bary[i] = wp.vec3(nan, nan, nan)
        return
    p, f, b = closest_point(mesh, x, max_dist)
    points[i] = p
    face[i] = f
    bary[i] = b
