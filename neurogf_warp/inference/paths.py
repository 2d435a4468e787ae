"""Shortest paths from the network's path head, their refinement on the surface, and projection of points onto
the SDF head's surface.

Paths are (N, m, 3) float32 points in mesh coordinates, ends included; see ``path`` for the refinement (on the
mesh when the model has one, else on the SDF head's surface), the choice among candidate paths (``surface_fit``)
and the projections ("mesh": the exact closest mesh point, the default with a mesh; "sdf": Newton steps on the
SDF head, mesh-free).
"""
from __future__ import annotations

import warnings

import numpy as np
import warp as wp

from neurogf_warp.common.arrays import Output, resolve_device
from neurogf_warp.inference.backends import CPU_CHUNK_ALIGN, backend_of, in_chunks
from neurogf_warp.inference.inputs import check_tensor, pair_components, pair_inputs, points_in, relative_points
from neurogf_warp.inference.state import QueryState, check_memory, query_state
from neurogf_warp.kernels.inference import finish, mlp
from neurogf_warp.kernels.inference import refine as refine_kernels
from neurogf_warp.mesh.surface import _flat_points, snap_to_mesh, warp_mesh
from neurogf_warp.model.model import Model

PROJECT_STEPS = 2  # Newton steps from a point near the surface; |sdf| falls ~10x per step (a trained SDF head)
JUMP_SPAN = 4  # chords per span in the gap test of refined candidates (the network's distance between span ends)
JUMP_TOL = 2.0  # a span may be at most this many mean point spacings longer along the surface than in space: on
# a 74 s CPU cow model legitimate chords came out <= 0.005 longer, chords that jump a gap 0.3-0.8 (spacing 0.06)
SHORT_OF = 0.8  # nor may a candidate be shorter than this share of the network's distance between its ends (no path
# on the surface is shorter than the geodesic; the margin covers the network's error: cow p99 5%)
SURFACE_TOL = 1.0  # a path follows the surface when no chord's midpoint is farther from it than one mean point
# spacing (beyond its ends' own distance): a legitimate chord across a crease leaves by at most half its length;
# a chord that jumps through the solid or across a gap leaves by about half the gap, far more than a spacing
PROJECTIONS = ("auto", None, "sdf", "mesh")


class PathWarning(UserWarning):
    """Some returned paths leave the surface: every candidate path of those pairs did."""


def path(model: Model, p, q, m: int = 128, refine: int = 0, project: str | None = "auto", return_faces: bool = False,
         device=None, precision: str = "auto", check: bool = True):
    """Shortest paths as m points each (ends included): (N, 3), (N, 3) -> (N, m, 3) float32 mesh coordinates.

    Straight-line samples between p and q go through the network's path head, which moves them toward the
    surface (not onto it: a head path can cut through the solid or float beside the surface). With a windowed
    path head (``path_window``) the ends are exactly p and q, else the network's. A path from a point to itself
    (rows with p == q) is that point repeated. Paths between different connected components are NaN rows. A
    single pair (3,), (3,) gives (m, 3).

    project: where the returned points lie.
      "auto" (default): "mesh" when the model has a mesh, else None. Without a mesh the head's points can lie
        off the surface (and a refined path's points on the SDF head's surface); "sdf" puts every point there,
        at the cost of about five SDF evaluations a point (on one CPU core that is 30x the head's own cost).
      "mesh": every point, ends included, snapped to the exact closest point of the mesh (``surface.snap_to_mesh``).
      "sdf": every point moved onto the SDF head's surface by Newton steps (mesh-free).
      None: the points as computed (the head's points, or the refined path).
    return_faces (with project "mesh", or "auto" with a mesh): also return, per point, the face it lies on
    ((N, m) int32, rows of the mesh's face list as given) and its barycentric coordinates ((N, m, 3) float32):
    (points, faces, bary).

    refine > 0 shortens the paths on the surface: on the mesh when the model has one (each inner point moved to
    the closest mesh point of its neighbours' midpoint, no network evaluations), else on the SDF head's surface
    (the midpoint moved by a Newton step, about four SDF evaluations a point). That many Jacobi sweeps at m/4,
    then m/2, then m points (ends pinned to p and q), from three starts: the head's path p -> q, its path q -> p
    and the straight line. Then, per pair, the result is the best of five candidates: the three refined paths,
    the head's path and the straight line, both moved onto the same surface. The best is the shortest of those
    that follow the surface (no chord's midpoint farther from the surface than the path's mean point spacing,
    beyond what its ends are: a chord that leaves by more jumps through the solid or across a gap); so refining
    never returns a longer path than the projected head path or the projected straight line, by that length.
    Where no candidate of a pair follows the surface, the one that leaves it least is returned and a
    ``PathWarning`` says how many pairs and how far (mesh units). With precision "fp16" the head paths and,
    without a mesh, the SDF values come from batched tensor-core launches.
    """
    if project not in PROJECTIONS:
        raise ValueError(f"project must be 'auto', None, 'sdf' or 'mesh', got {project!r}")
    if project == "auto":
        project = "mesh" if model.mesh is not None else None
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
    _check_memory(dev, n, m, refine, return_faces or project == "mesh")
    out = Output(kind, dev)
    res = out.empty((n, m), dtype=wp.vec3)
    if n and (refine or project == "sdf") and frame is not st.frame:
        # iterated points (refinement, Newton steps) live relative to the mesh centre, where float32 resolves the
        # mesh's own scale; device input is moved there once (float64 arithmetic) and the result moved back below
        P, Q, frame = relative_points(model, P, frame), relative_points(model, Q, frame), st.frame
    faces = bary = None
    if project == "mesh":
        faces = wp.empty((n, m), dtype=wp.int32, device=dev)
        bary = wp.empty((n, m), dtype=wp.vec3, device=dev)
    left = []  # refined pairs whose every candidate left the surface: (count, largest excess) per chunk

    def rows(lo, hi):  # pairs lo..hi: every pair's path depends on its own ends only
        k, p_, q_, r = hi - lo, P[lo:hi], Q[lo:hi], res[lo:hi]
        chunk_left = None
        if not refine:
            be.paths(p_, q_, r, frame)
        else:
            chunk_left = _refined_paths(st, be, p_, q_, r, int(refine), dev, frame)
        # NaN rows for unchecked ends outside the domain (before any projection: NaN stays NaN), p == q rows
        st.launches.run(finish.finish_paths, k, {"ps": p_, "qs": q_, "frame": frame, "test_domain": int(not check),
                                                 "x": r}, group="finish_paths")
        flat = r.reshape(-1)
        if project == "sdf":
            wp.launch(mlp.project_points, flat.shape[0], inputs=[st.weights, flat, frame, 2 * PROJECT_STEPS],
                      outputs=[flat], device=dev)
        # host input ran relative to the mesh centre: back to mesh coordinates (float64 sum) before anything below
        # reads the points
        if frame is st.frame and st.model.in_mesh_frame:
            wp.launch(finish.shift_points, flat.shape[0], inputs=[flat, wp.vec3d(*st.center)], outputs=[flat],
                      device=dev)
        if project == "mesh":
            snapped, f, b = snap_to_mesh(model, r, device=dev, check=False)  # NaN rows stay NaN
            wp.copy(r, snapped)
            wp.copy(faces[lo:hi], f)
            wp.copy(bary[lo:hi], b)
        comps = pair_components(model, p_, q_, dev, frame)
        if comps is not None:
            wp.launch(finish.split_paths, (k, m), inputs=[*comps, r], device=dev)
        if chunk_left is not None:
            left.append(_left_pairs(chunk_left, p_, q_, comps))

    # CPU: chunks of pairs, so that Ctrl-C stops a long query within about a second (results as one launch)
    first = max(1, (1 << 14) // (m * (5 * (1 + int(refine)) if refine else 1)))
    in_chunks(dev, n, rows, first=first, align=CPU_CHUNK_ALIGN if be.precision == "fp16" else 1)
    if left:
        _warn_left([c for c, _ in left], [x for _, x in left], n)
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


def _check_memory(dev, n: int, m: int, refine: int, snapped: bool):
    """A MemoryError naming ``m`` and the pairs, before any allocation, where the paths cannot fit: the result
    (12 bytes a point), the faces and weights of snapped points (16), and refinement's five candidates (~9x)."""
    per_point = 12 * (9 if refine else 1) + (16 if snapped else 0)
    need = n * m * per_point
    what = f"{n:,} paths of m={m:,} points"
    hint = "ask fewer points per path (m=) or pass fewer pairs per call"
    if dev.is_cuda:
        check_memory(dev, need, what, hint)
        return
    import os

    try:
        free = os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):  # not reported on this system
        return
    if need > 0.9 * free:
        raise MemoryError(f"{what} need {need / 1e9:.2f} GB, but {free / 1e9:.2f} GB of memory is free: {hint}")


def _relative_mesh(st: QueryState) -> wp.Mesh:
    """The mesh as a ``wp.Mesh`` in the state's frame (vertices relative to the mesh centre, the coordinates of
    refinement), made once per state."""
    md = st.mesh("refined paths")
    if md._wp_mesh is None:  # a one-part mesh has none yet (components need no closest points there)
        faces = st.model.mesh.internal_faces.reshape(-1).astype(np.int32)
        md._wp_mesh = wp.Mesh(points=md.verts, indices=wp.array(faces, dtype=wp.int32, device=st.device))
    return md._wp_mesh


def _refined_paths(st: QueryState, be, P, Q, res, refine: int, dev, frame):
    """Refined paths into res (N, m) (see ``path``); returns, per pair, how far (mesh units) the chosen path's
    chords leave the surface where no candidate followed it, else 0: (N,) float32."""
    n, m = res.shape
    levels = _levels(m)
    on_mesh = st.model.mesh is not None
    # candidates at m points, rows c * n + i: 0-2 refined from the head p -> q, the head q -> p and the straight
    # line; 3 the head p -> q; 4 the straight line (3 and 4 moved onto the surface below)
    full = wp.empty((5 * n, m), dtype=wp.vec3, device=dev)
    be.paths(P, Q, full[3 * n:4 * n], frame)
    wp.launch(mlp.straight_paths, (n, m), inputs=[P, Q], outputs=[full[4 * n:]], device=dev)
    starts, ends = wp.empty(5 * n, dtype=wp.vec3, device=dev), wp.empty(5 * n, dtype=wp.vec3, device=dev)
    for c, (a, b) in enumerate(((P, Q), (Q, P), (P, Q), (P, Q), (P, Q))):
        wp.copy(starts, a, dest_offset=c * n, count=n)
        wp.copy(ends, b, dest_offset=c * n, count=n)
    cand = wp.empty((3 * n, levels[0]), dtype=wp.vec3, device=dev)
    wp.launch(mlp.resample_paths, (n, levels[0]), inputs=[full[3 * n:4 * n]], outputs=[cand[:n]], device=dev)
    be.paths(Q, P, cand[n:2 * n], frame)
    wp.launch(mlp.straight_paths, (n, levels[0]), inputs=[P, Q], outputs=[cand[2 * n:]], device=dev)
    # the points are in the state's frame (relative to the mesh centre): the mesh too
    mesh_id = _relative_mesh(st).id if on_mesh else None
    if on_mesh:
        cand = _shorten_on_mesh(mesh_id, cand, starts, ends, levels, refine, dev)
        wp.launch(refine_kernels.snap_inner, (2 * n, m), inputs=[mesh_id, starts[3 * n:], ends[3 * n:]],
                  outputs=[full[3 * n:]], device=dev)
    else:
        cand = _shorten_on_sdf(be, cand, starts, ends, levels, refine, dev, frame, full[3 * n:])
    wp.copy(full, cand, count=3 * n * m)
    # score every candidate: its length along the surface, and how far its chords leave the surface
    if on_mesh:
        length, excess = _fit(be, full, dev, frame, mesh_id)
    else:
        s_start, s_end = wp.empty(5 * n, dtype=wp.float32, device=dev), wp.empty(5 * n, dtype=wp.float32, device=dev)
        be.sdf(starts, s_start, frame)
        be.sdf(ends, s_end, frame)
        off = wp.zeros((5 * n, m), dtype=wp.float32, device=dev)  # inner points: on the SDF surface (projected)
        wp.launch(refine_kernels.end_offsets, 5 * n, inputs=[s_start, s_end], outputs=[off], device=dev)
        length, excess = _fit(be, full, dev, frame, None, off)
    _fold_jumps(be, full, excess, dev, frame, length, P, Q)
    best, left = wp.empty(n, dtype=wp.int32, device=dev), wp.empty(n, dtype=wp.float32, device=dev)
    wp.launch(refine_kernels.pick_best, n, inputs=[length, excess, 5, m, SURFACE_TOL], outputs=[best, left],
              device=dev)
    rev = wp.array([0, 1, 0, 0, 0], dtype=wp.int32, device=dev)
    wp.launch(refine_kernels.take_best, (n, m), inputs=[full, best, rev], outputs=[res], device=dev)
    return left


def _fold_jumps(be, x, excess, dev, frame, length, P, Q):
    """Count, in ``excess``, the spans of candidate paths x (N, m) that jump a gap. Snapping to the closest surface
    point lets a sweep (or a snapped straight line) cross a gap narrower than a point spacing, between a leg and the
    body or across a thin slot: every chord then stays near the surface, yet the path is shorter than the geodesic
    (a cow model: 15-20% on 6 of 64 pairs, and twice the head's Chamfer distance to the solver's paths). Such a
    span's ends are far apart along the surface: the network's distance between them exceeds their straight
    distance by much more than a legitimate chord's (<= 0.005, a tenth of a point spacing, there); that excess,
    divided by JUMP_TOL, is held to the same tolerance as the chords' distance from the surface. A gap can also
    lie where the network's own field is smooth across it (a cow pair: a path of 2.35 between ends 5.6 apart on the
    surface, every span unremarkable): a candidate shorter than SHORT_OF times the network's distance between its
    ends P, Q (``length``: the candidates' lengths along the surface) counts as leaving too."""
    n, m = x.shape
    k = -(-(m - 1) // JUMP_SPAN)
    a, b = wp.empty((n, k), dtype=wp.vec3, device=dev), wp.empty((n, k), dtype=wp.vec3, device=dev)
    wp.launch(refine_kernels.span_ends, (n, k), inputs=[x, JUMP_SPAN], outputs=[a, b], device=dev)
    d = wp.empty((n, k), dtype=wp.float32, device=dev)
    be.pairs(a.reshape(-1), b.reshape(-1), d.reshape(-1), False, frame)
    d_ends = wp.empty(P.shape[0], dtype=wp.float32, device=dev)
    be.pairs(P, Q, d_ends, False, frame)
    wp.launch(refine_kernels.fold_jumps, n, inputs=[a, b, d, length, d_ends, SHORT_OF, SURFACE_TOL / JUMP_TOL],
              outputs=[excess], device=dev)


def _shorten_on_mesh(mesh_id, cand, starts, ends, levels, refine: int, dev):
    """Jacobi shortening sweeps on the mesh (``mesh_id``, in the points' frame) at each level's point count;
    returns the (3N, m) result."""
    for level, ml in enumerate(levels):
        if level:
            finer = wp.empty((cand.shape[0], ml), dtype=wp.vec3, device=dev)
            wp.launch(mlp.resample_paths, finer.shape, inputs=[cand], outputs=[finer], device=dev)
            cand = finer
        wp.launch(refine_kernels.snap_inner, cand.shape, inputs=[mesh_id, starts, ends], outputs=[cand], device=dev)
        tmp = wp.empty_like(cand)
        for _ in range(refine):
            wp.launch(refine_kernels.relax_on_mesh, cand.shape, inputs=[mesh_id, cand], outputs=[tmp], device=dev)
            cand, tmp = tmp, cand
    return cand


def _shorten_on_sdf(be, cand, starts, ends, levels, refine: int, dev, frame, others):
    """Shortening sweeps on the SDF head's surface at each level's point count (the (3N, m) result), and
    ``others`` (2N, m) (the head's and the straight paths) projected onto that surface in place; the backend's
    ``settle`` (Newton steps, ends pinned) and ``sweep`` (each inner point to its neighbours' projected midpoint)."""
    n3 = cand.shape[0]
    scratch = {}
    for level, ml in enumerate(levels):
        if level:
            finer = wp.empty((n3, ml), dtype=wp.vec3, device=dev)
            wp.launch(mlp.resample_paths, finer.shape, inputs=[cand], outputs=[finer], device=dev)
            cand = finer
        cand = be.settle(cand, starts, ends, PROJECT_STEPS, scratch, frame)
        for _ in range(refine):
            cand = be.sweep(cand, starts, ends, scratch, frame)
    # a sweep takes one Newton step from the midpoint; at a crease the chord's midpoint lies deeper than
    # one step reaches, so the result gets a full projection
    cand = be.settle(cand, starts, ends, 2 * PROJECT_STEPS, scratch, frame)
    wp.copy(others, be.settle(others, starts[n3:], ends[n3:], 2 * PROJECT_STEPS, {}, frame))
    return cand


def surface_fit(model: Model, paths, device=None, precision: str = "auto"):
    """How well polylines follow the surface: (N, m, 3) mesh coordinates -> (length, excess), each (N,) float32,
    mesh units; the criterion by which ``path(..., refine=...)`` picks its paths, usable on any paths.

    The surface is the mesh when the model has one, else the SDF head's zero level set. excess: the largest,
    over the path's chords, of the chord midpoint's distance from the surface less the mean of its two ends'
    distances (0 or less: the chords hug the surface; a chord through the solid or across a gap leaves it by
    about half the gap). length: the length along the surface, each chord of length s counted as
    2 sqrt((s / 2)^2 + max(excess_j, 0)^2) (the chord bent to pass its own excess off its midpoint), so that
    cutting a crease or zigzagging across one does not look short. A path "follows the surface" in ``path``'s
    sense when excess <= SURFACE_TOL * length / (m - 1). NaN points give NaN.
    """
    dev = resolve_device(device, like=paths)
    x, kind, lead = _flat_points(paths, "paths", dev)
    if len(lead) != 2 or lead[1] < 2:
        raise ValueError(f"paths must have shape (N, m, 3) with m >= 2, got {lead + (3,)}")
    out = Output(kind, dev)
    n = lead[0]
    if not n:
        return out.result(out.empty(0)), out.result(out.empty(0))
    st = query_state(model, dev)
    mesh_id = warp_mesh(model.mesh, dev).id if model.mesh is not None else None  # mesh coordinates, as the paths
    be, x = backend_of(st, precision), x.reshape(lead)
    length, excess = out.empty(n), out.empty(n)

    def rows(lo, hi):  # CPU: chunks of paths (Ctrl-C within about a second); every path on its own
        a, b = _fit(be, x[lo:hi], dev, st.user_frame, mesh_id)
        wp.copy(length[lo:hi], a)
        wp.copy(excess[lo:hi], b)

    in_chunks(dev, n, rows, first=max(1, (1 << 14) // lead[1]), align=1)
    return out.result(length), out.result(excess)


def _fit(be, x, dev, frame, mesh_id, off=None):
    """(length along the surface, excess) of paths x (N, m) (see ``surface_fit``): on the mesh ``mesh_id`` (in the
    paths' coordinates) when given, else on the SDF head's surface (backend ``be``, points in ``frame``); ``off``:
    the points' SDF values when known, else computed."""
    n, m = x.shape
    gap = wp.zeros((n, m), dtype=wp.float32, device=dev)
    if mesh_id is not None:
        off = wp.zeros((n, m), dtype=wp.float32, device=dev)
        wp.launch(refine_kernels.gaps_on_mesh, x.shape, inputs=[mesh_id, x], outputs=[off, gap], device=dev)
    else:
        mids = wp.empty_like(x)
        wp.launch(refine_kernels.midpoints, x.shape, inputs=[x], outputs=[mids], device=dev)
        be.sdf(mids.reshape(-1), gap.reshape(-1), frame)
        if off is None:
            off = wp.empty((n, m), dtype=wp.float32, device=dev)
            be.sdf(x.contiguous().reshape(-1), off.reshape(-1), frame)
    length, excess = wp.empty(n, dtype=wp.float32, device=dev), wp.empty(n, dtype=wp.float32, device=dev)
    wp.launch(refine_kernels.score_paths, n, inputs=[x, off, gap], outputs=[length, excess], device=dev)
    return length, excess


def _left_pairs(left, P, Q, comps) -> tuple:
    """(how many pairs (of one component, p != q) had every candidate path leave the surface, the largest such
    excess, mesh units) of one chunk of refined paths."""
    ex = left.numpy()
    if not np.any(ex > 0):
        return 0, 0.0
    keep = np.any(P.numpy() != Q.numpy(), axis=1)
    if comps is not None:
        keep &= comps[0].numpy() == comps[1].numpy()
    bad = (ex > 0) & keep
    return int(bad.sum()), float(ex[bad].max()) if bad.any() else 0.0


def _warn_left(counts, worst, total: int | None = None):
    """A PathWarning for the pairs whose every candidate path left the surface (counts and worst excess by chunk)."""
    n_bad = int(sum(counts))
    if n_bad:
        warnings.warn(f"{n_bad} of {total} refined paths leave the surface: no candidate path of those "
                      f"pairs followed it (chord midpoints up to {max(worst):.3g} mesh units farther from "
                      f"the surface than their ends); they come back as the candidate that left it least",
                      PathWarning, stacklevel=3)


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
    check_tensor(x, "x")
    dev = resolve_device(device, like=x)
    X, kind, single, frame = points_in(model, x, "x", dev)
    out = Output(kind, dev)
    res = out.empty(X.shape[0], dtype=wp.vec3)
    if X.shape[0]:
        st = query_state(model, dev)
        X, frame = relative_points(model, X, frame), st.frame  # Newton steps relative to the mesh centre
        def rows(lo, hi):  # CPU: chunks (Ctrl-C within about a second); every point on its own
            wp.launch(mlp.project_points, hi - lo, inputs=[st.weights, X[lo:hi], frame, int(steps)],
                      outputs=[res[lo:hi]], device=dev)
            if frame is st.frame and st.model.in_mesh_frame:  # host input ran relative to the mesh centre
                wp.launch(finish.shift_points, hi - lo, inputs=[res[lo:hi], wp.vec3d(*st.center)],
                          outputs=[res[lo:hi]], device=dev)

        in_chunks(dev, X.shape[0], rows, first=1 << 12, align=1)
    if kind == "torch":
        r = wp.to_torch(res).view(-1, 3)
    elif kind == "warp":
        r = res
    else:
        r = res.numpy()
    return r[0] if single else r
