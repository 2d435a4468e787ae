"""Shortest paths from the network's path head, their refinement on the SDF head's surface, and projection of
points onto that surface.

Paths are (N, m, 3) float32 points in mesh coordinates, ends included; see ``path`` for the refinement schedule
and the projections ("sdf": Newton steps on the SDF head, mesh-free; "mesh": the exact closest mesh point).
"""
from __future__ import annotations

import numpy as np
import warp as wp

from neurogf_warp.common.arrays import Output, resolve_device
from neurogf_warp.inference.inputs import pair_components, pair_inputs, points_in, relative_points
from neurogf_warp.inference.backends import backend_of
from neurogf_warp.inference.state import query_state
from neurogf_warp.kernels.inference import finish, mlp
from neurogf_warp.model.model import Model

PROJECT_STEPS = 2  # Newton steps from a point near the surface; |sdf| falls ~10x per step (a trained SDF head)


def path(model: Model, p, q, m: int = 128, refine: int = 0, project: str | None = None, return_faces: bool = False,
         device=None, precision: str = "auto", check: bool = True):
    """Shortest paths as m points each (ends included): (N, 3), (N, 3) -> (N, m, 3) float32 mesh coordinates.

    Straight-line samples between p and q go through the network's path head, which moves them onto the
    surface. With a windowed path head (``path_window``) the ends are exactly p and q, else the network's.
    Paths between different connected components are NaN rows. A single pair (3,), (3,) gives (m, 3).

    refine > 0 shortens the paths on the SDF head's surface: that many sweeps (each inner point to the
    projected midpoint of its neighbours, ends pinned to p and q) at m/4, then m/2, then m points, from
    three starts: the head's path p -> q, its path q -> p, and the straight line; the shortest result that
    does not jump between sheets is kept. 25-50 sweeps suffice for m=128 (benchmarks/RESULTS.md); a sweep
    costs about as much as four SDF queries per point. With precision "fp16" the SDF values come from batched
    tensor-core launches (points end within ~2e-4 of the SDF surface, normalized frame; fp32: ~2e-5).

    project: None (the points as computed), "sdf" (every point moved onto the SDF head's surface by Newton steps:
    mesh-free) or "mesh" (every point snapped to the exact closest point of the mesh, ``surface.snap_to_mesh``).
    return_faces (with project="mesh"): also return, per point, the face it lies on ((N, m) int32, rows of the
    mesh's face list as given) and its barycentric coordinates ((N, m, 3) float32): (points, faces, bary).
    """
    if project not in (None, "sdf", "mesh"):
        raise ValueError(f"project must be None, 'sdf' or 'mesh', got {project!r}")
    if return_faces and project != "mesh":
        raise ValueError("return_faces=True needs project='mesh' (faces are those of the mesh)")
    if project == "mesh" and model.mesh is None:
        raise ValueError("project='mesh' needs the model's mesh: load it with neurogf_warp.load(path, mesh=...), or "
                         "use project='sdf'")
    if not isinstance(m, (int, np.integer)) or isinstance(m, bool) or m < 2:
        raise ValueError(f"m (points per path) must be an integer >= 2, got {m!r}")
    if not isinstance(refine, (int, np.integer)) or isinstance(refine, bool) or refine < 0:
        raise ValueError(f"refine (shortening sweeps) must be an integer >= 0, got {refine!r}")
    dev, P, Q, kind, single, frame = pair_inputs(model, p, q, device, check)
    st = query_state(model, dev)
    be = backend_of(st, precision)
    n, m = P.shape[0], int(m)
    out = Output(kind, dev)
    res = out.empty((n, m), dtype=wp.vec3)
    if n and (refine or project == "sdf") and frame is not st.frame:
        # iterated points (refinement, Newton steps) live relative to the mesh centre, where float32 resolves the
        # mesh's own scale; device input is moved there once (float64 arithmetic) and the result moved back below
        P, Q, frame = relative_points(model, P, frame), relative_points(model, Q, frame), st.frame
    if n and not refine:
        be.paths(P, Q, res, frame)
    elif n:
        _refined_paths(be, P, Q, res, int(refine), dev, frame)
    if n and project == "sdf":
        flat = res.reshape(-1)
        wp.launch(mlp.project_points, flat.shape[0], inputs=[st.weights, flat, frame, 2 * PROJECT_STEPS],
                  outputs=[flat], device=dev)
    if n:
        # NaN rows for ends outside the domain (check=False); host input ran relative to the mesh centre:
        # back to mesh coordinates (float64 sum) before anything below reads the points
        wp.launch(finish.nan_paths, (n, m), inputs=[P, Q, frame], outputs=[res], device=dev)
        if frame is st.frame and st.model.in_mesh_frame:
            flat = res.reshape(-1)
            wp.launch(finish.shift_points, flat.shape[0], inputs=[flat, wp.vec3d(*st.center)], outputs=[flat],
                      device=dev)
    faces = None
    if n and project == "mesh":
        from neurogf_warp.mesh.surface import snap_to_mesh

        snapped, faces, bary = snap_to_mesh(model, res, device=dev)
        wp.copy(res, snapped)
    if n:
        comps = pair_components(model, P, Q, dev, frame)
        if comps is not None:
            wp.launch(finish.split_paths, (n, m), inputs=[*comps, res], device=dev)
    if kind == "torch":
        r = wp.to_torch(res).view(n, m, 3)
    elif kind == "warp":
        r = res
    else:
        r = res.numpy()
    if return_faces:
        conv = (lambda a: wp.to_torch(a)) if kind == "torch" else (lambda a: a) if kind == "warp" else \
            (lambda a: a.numpy())
        f, b = conv(faces.reshape((n, m))), conv(bary.reshape((n, m)))
        if kind == "torch":
            b = b.view(n, m, 3)
        return (r[0], f[0], b[0]) if single else (r, f, b)
    return r[0] if single else r


def _refined_paths(be, P, Q, res, refine: int, dev, frame):
    """The refinement schedule of ``path`` on backend ``be`` (its ``settle`` and ``sweep`` steps)."""
    n, m = res.shape
    levels = _levels(m)
    cand = wp.empty((3 * n, levels[0]), dtype=wp.vec3, device=dev)
    be.paths(P, Q, cand[:n], frame)
    be.paths(Q, P, cand[n:2 * n], frame)
    wp.launch(mlp.straight_paths, (n, levels[0]), inputs=[P, Q], outputs=[cand[2 * n:]], device=dev)
    starts, ends = wp.empty(3 * n, dtype=wp.vec3, device=dev), wp.empty(3 * n, dtype=wp.vec3, device=dev)
    for c, (a, b) in enumerate(((P, Q), (Q, P), (P, Q))):
        wp.copy(starts, a, dest_offset=c * n, count=n)
        wp.copy(ends, b, dest_offset=c * n, count=n)
    scratch = {}
    for level, ml in enumerate(levels):
        if level:
            finer = wp.empty((3 * n, ml), dtype=wp.vec3, device=dev)
            wp.launch(mlp.resample_paths, finer.shape, inputs=[cand], outputs=[finer], device=dev)
            cand = finer
        cand = be.settle(cand, starts, ends, PROJECT_STEPS, scratch, frame)
        for _ in range(refine):
            cand = be.sweep(cand, starts, ends, scratch, frame)
    # a sweep takes one Newton step from the midpoint; at a crease the chord's midpoint lies deeper than
    # one step reaches, so the result gets a full projection
    cand = be.settle(cand, starts, ends, 2 * PROJECT_STEPS, scratch, frame)
    rev = wp.array([0, 1, 0], dtype=wp.int32, device=dev)
    wp.launch(mlp.pick_shortest, (n, m), inputs=[cand, 3, rev], outputs=[res], device=dev)


def _levels(m: int) -> list:
    """Point counts of the coarse-to-fine refinement: m/4, m/2, m (none under 8). Jacobi sweeps straighten a
    chain of k points in ~k^2 sweeps; the coarse levels do the long-range part cheaply."""
    out = [m]
    while len(out) < 3 and out[0] // 2 >= 8:
        out.insert(0, out[0] // 2)
    return out


def project(model: Model, x, steps: int = PROJECT_STEPS, device=None):
    """Points moved onto the surface of the network's SDF head (Newton steps on its zero level set): (N, 3) -> (N, 3)."""
    if not isinstance(steps, (int, np.integer)) or isinstance(steps, bool) or steps < 0:
        raise ValueError(f"steps must be an integer >= 0, got {steps!r}")
    dev = resolve_device(device, like=x)
    X, kind, single, frame = points_in(model, x, "x", dev)
    out = Output(kind, dev)
    res = out.empty(X.shape[0], dtype=wp.vec3)
    if X.shape[0]:
        st = query_state(model, dev)
        X, frame = relative_points(model, X, frame), st.frame  # Newton steps relative to the mesh centre
        wp.launch(mlp.project_points, X.shape[0], inputs=[st.weights, X, frame, int(steps)], outputs=[res],
                  device=dev)
        if frame is st.frame and st.model.in_mesh_frame:  # host input ran relative to the mesh centre
            wp.launch(finish.shift_points, X.shape[0], inputs=[res, wp.vec3d(*st.center)], outputs=[res],
                      device=dev)
    if kind == "torch":
        r = wp.to_torch(res).view(-1, 3)
    elif kind == "warp":
        r = res
    else:
        r = res.numpy()
    return r[0] if single else r
