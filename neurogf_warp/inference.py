"""Queries of a trained NeuroGF, run by the Warp kernels in ``neurogf_warp.kernels.mlp``.

With a mesh attached, points are in the mesh's coordinates and distances in its units, and per-vertex
outputs follow the mesh's own vertex numbering (NaN for vertices no face uses).
"""
from __future__ import annotations

import numpy as np
import torch
import warp as wp

from .arrays import Output, as_points, resolve_device
from .kernels import mlp, ssad_tile
from .model import Model

__all__ = ["fold_batchnorm", "warp_weights", "ssad", "msad", "distance", "sdf", "path", "embed"]

BN_EPS = 1e-5


def fold_batchnorm(layer) -> tuple[np.ndarray, np.ndarray | None]:
    """(W', b') in float64 with eval-mode BatchNorm folded in: W' = diag(s) W, b' = beta - mu s."""
    mod = layer.linear if hasattr(layer, "linear") else layer.conv
    w = mod.weight.detach().double().cpu().reshape(mod.weight.shape[0], -1)
    if layer.bn is None:
        return w.numpy(), None
    bn = layer.bn
    s = bn.weight.detach().double().cpu() / torch.sqrt(bn.running_var.detach().double().cpu() + BN_EPS)
    b = bn.bias.detach().double().cpu() - bn.running_mean.detach().double().cpu() * s
    return (w * s[:, None]).numpy(), b.numpy()


def _layers(net):
    return {"l": list(net.lifting), "g": list(net.gdf_head), "s": list(net.sdf_head),
            "c": [net.cdw_fc], "p": list(net.spf_head)}


def warp_weights(model: Model, device=None) -> mlp.NeuroGFWeights:
    """The model's folded float32 weights on ``device`` (cached; call ``model.invalidate()`` after edits)."""
    dev = resolve_device(device)
    key = ("weights", str(dev))
    if key not in model._warp:
        w = mlp.NeuroGFWeights()
        for prefix, layers in _layers(model.net).items():
            for i, layer in enumerate(layers):
                W, b = fold_batchnorm(layer)
                name = f"{prefix}{i}" if prefix != "c" else "c"
                setattr(w, f"{name}_w", wp.array(W.astype(np.float32), dtype=wp.float32, device=dev))
                if b is not None:
                    setattr(w, f"{name}_b", wp.array(b.astype(np.float32), dtype=wp.float32, device=dev))
        w.euclid = 1.0 if model.net.euclid else 0.0
        w.residual = 1.0 if model.net.path_residual else 0.0
        w.window = 1.0 if model.net.path_window else 0.0
        model._warp[key] = w
    return model._warp[key]


def _frame(model: Model) -> mlp.Frame:
    f = mlp.Frame()
    if model.in_mesh_frame:
        f.center = wp.vec3(*model.center.astype(np.float32))
        f.xscale = float(model.scale)
        f.dscale = float(1.0 / model.scale)
    else:
        f.center = wp.vec3(0.0, 0.0, 0.0)
        f.xscale = 1.0
        f.dscale = 1.0
    return f


def _vertices(model: Model, dev):
    """Mesh vertices (user frame, float32) and their positions in the user's numbering, cached per device."""
    if model.mesh is None:
        raise ValueError("this model has no mesh, so it has no vertices to measure to: load it with "
                         "neurogf_warp.load(path, mesh=...) or query points with neurogf_warp.distance()")
    key = ("verts", str(dev))
    if key not in model._warp:
        m = model.mesh
        model._warp[key] = (wp.array(m.vertices.astype(np.float32), dtype=wp.vec3, device=dev),
                            wp.array(m.index.astype(np.int32), dtype=wp.int32, device=dev))
    return model._warp[key]


def _source_points(model: Model, src, name: str) -> np.ndarray:
    """Sources as (S, 3) points in the user frame: vertex indices (user numbering) or 3-D points."""
    if isinstance(src, wp.array):
        src = src.numpy()
    elif isinstance(src, torch.Tensor):
        src = src.detach().cpu().numpy()
    a = np.asarray(src)
    if np.issubdtype(a.dtype, np.integer):
        if model.mesh is None:
            raise ValueError(f"{name} given as vertex indices, but this model has no mesh: pass points instead")
        return model.mesh.vertices[model.mesh.vertex(a.reshape(-1))]
    if not np.issubdtype(a.dtype, np.floating):
        raise TypeError(f"{name} must be vertex indices (integers) or points (floats), got dtype {a.dtype}")
    a = a.reshape(1, 3) if a.shape == (3,) else a
    if a.ndim != 2 or a.shape[1] != 3:
        raise ValueError(f"{name} must be vertex indices or points of shape (S, 3), got shape {np.shape(src)}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name} contains non-finite coordinates (NaN or inf)")
    return a.astype(np.float64)


def embed(model: Model, x, device=None) -> wp.array:
    """Point embeddings e(x), shape (N, D), as a wp.array on the device."""
    dev = resolve_device(device, like=x)
    pts, _ = as_points(x, "x", dev, single=True)
    out = wp.empty((pts.shape[0], model.D), dtype=wp.float32, device=dev)
    wp.launch(mlp.embed_points, pts.shape[0], inputs=[warp_weights(model, dev), pts, _frame(model)],
              outputs=[out], device=dev)
    return out


def ssad(model: Model, src, device=None, output: str = "numpy"):
    """Single source, all destinations: predicted geodesic distance from ``src`` to every mesh vertex.

    src: a vertex index (the mesh's numbering) or a 3-D point in mesh coordinates.
    Returns one value per vertex of the mesh as given (NaN where no face uses the vertex).
    For D <= 256 the first call embeds every vertex and keeps the result with the model (V x D float32 per
    device); later calls run only the distance head, as tile GEMMs (``kernels/ssad_tile.py``).
    """
    a = np.asarray(src.detach().cpu() if isinstance(src, torch.Tensor) else src)
    if np.issubdtype(a.dtype, np.integer) and a.size != 1:
        raise ValueError(f"ssad takes one source, got {a.size}; use msad for several")
    if np.issubdtype(a.dtype, np.floating) and a.size != 3:
        raise ValueError(f"ssad takes one source point of 3 coordinates, got shape {a.shape}")
    if model.mesh is not None and model.D <= ssad_tile.MAX_D:
        return _ssad_tile(model, src, resolve_device(device), output)
    return _to_vertices(model, src, "ssad", "src", mlp.distance_to_source, device, output)


def _ssad_tile(model: Model, src, dev, output: str = "numpy", mathdx: bool = False, block: int = ssad_tile.BLOCK,
               chunk: int = ssad_tile.CHUNK, threads: int = ssad_tile.THREADS):
    """SSAD through the tile kernel: vertex embeddings cached per model and device (V x D float32, e.g. 455 MB
    for 444K vertices at D=256), so a query runs only the distance head as tile GEMMs."""
    verts, index = _vertices(model, dev)
    key = ("tile_ssad", str(dev))
    if key not in model._warp:
        w = warp_weights(model, dev)
        ex = embed(model, verts, dev)
        col = lambda b: wp.array(b.numpy().reshape(-1, 1), dtype=wp.float32, device=dev)
        model._warp[key] = (ex, (w.g0_w, col(w.g0_b), w.g1_w, col(w.g1_b), w.g2_w))
    ex, weights = model._warp[key]
    pts = _source_points(model, src, "src")
    es = embed(model, pts, dev)
    n, (H, D) = verts.shape[0], weights[0].shape
    head = wp.empty((1, n), dtype=wp.float32, device=dev)
    wp.launch_tiled(ssad_tile.head_kernel(D, H, mathdx, block, chunk), dim=[(n + block - 1) // block],
                    inputs=[es, ex, *weights, D // chunk], outputs=[head], block_dim=threads, device=dev)
    out = Output(output, dev)
    res = out.empty(model.mesh.n_input, fill=float("nan"))
    wp.launch(ssad_tile.finish, n, inputs=[head, wp.vec3(*pts[0].astype(np.float32)), verts, _frame(model),
                                           1.0 if model.net.euclid else 0.0, index], outputs=[res], device=dev)
    return out.result(res)


def msad(model: Model, sources, device=None, output: str = "numpy"):
    """Multiple sources, all destinations: distance from every mesh vertex to its nearest source."""
    return _to_vertices(model, sources, "msad", "sources", mlp.distance_to_nearest_source, device, output)


def _to_vertices(model, src, what, name, kernel, device, output):
    if model.mesh is None:
        raise ValueError(f"{what} needs the model's mesh: load the model with neurogf_warp.load(path, mesh=...)")
    dev = resolve_device(device)
    pts = _source_points(model, src, name)
    es = embed(model, pts, dev)
    verts, index = _vertices(model, dev)
    out = Output(output, dev)
    res = out.empty(model.mesh.n_input, fill=float("nan"))
    srcs = wp.array(pts.astype(np.float32), dtype=wp.vec3, device=dev)
    wp.launch(kernel, verts.shape[0], inputs=[warp_weights(model, dev), es, srcs, verts, _frame(model), index],
              outputs=[res], device=dev)
    return out.result(res)


def _pair_inputs(model, p, q, device):
    dev = resolve_device(device, like=p)
    P, kind = as_points(p, "p", dev)
    Q, _ = as_points(q, "q", dev)
    if P.shape != Q.shape:
        raise ValueError(f"p and q must have the same shape (N, 3), got {P.shape[0]} and {Q.shape[0]} points")
    return dev, P, Q, kind


def distance(model: Model, p, q, device=None):
    """Batched point-to-point geodesic distances: (N, 3), (N, 3) -> (N,). Symmetric by construction."""
    dev, P, Q, kind = _pair_inputs(model, p, q, device)
    out = Output(kind, dev)
    res = out.empty(P.shape[0])
    wp.launch(mlp.distance_pairs, P.shape[0], inputs=[warp_weights(model, dev), P, Q, _frame(model)],
              outputs=[res], device=dev)
    return out.result(res)


def sdf(model: Model, x, device=None):
    """Signed distance from the network's SDF head (negative inside): (N, 3) -> (N,)."""
    dev = resolve_device(device, like=x)
    X, kind = as_points(x, "x", dev)
    out = Output(kind, dev)
    res = out.empty(X.shape[0])
    wp.launch(mlp.signed_distances, X.shape[0], inputs=[warp_weights(model, dev), X, _frame(model)],
              outputs=[res], device=dev)
    return out.result(res)


def path(model: Model, p, q, m: int = 128, refine: int = 0, device=None):
    """Shortest paths as m points each (ends included): (N, 3), (N, 3) -> (N, m, 3).

    Straight-line samples between p and q go through the network's path head, which moves them onto the
    surface. With a windowed path head (``path_window``) the ends are exactly p and q, else the network's.

    refine > 0 shortens the paths on the SDF head's surface: that many sweeps (each inner point to the
    projected midpoint of its neighbours, ends pinned to p and q) at m/4, then m/2, then m points, from
    three starts: the head's path p -> q, its path q -> p, and the straight line; the shortest result that
    does not jump between sheets is kept. 25-50 sweeps suffice for m=128 (benchmarks/RESULTS.md); a sweep
    costs about as much as four SDF queries per point. The refined paths are locally shortest on the surface.
    """
    if not isinstance(m, (int, np.integer)) or m < 2:
        raise ValueError(f"m (points per path) must be an integer >= 2, got {m!r}")
    if not isinstance(refine, (int, np.integer)) or refine < 0:
        raise ValueError(f"refine (shortening sweeps) must be an integer >= 0, got {refine!r}")
    dev, P, Q, kind = _pair_inputs(model, p, q, device)
    n, m = P.shape[0], int(m)
    out = Output(kind, dev)
    res = out.empty((n, m), dtype=wp.vec3)
    if n and not refine:
        _head_paths(model, P, Q, res, dev)
    elif n:
        w, frame, levels = warp_weights(model, dev), _frame(model), _levels(m)
        cand = wp.empty((3 * n, levels[0]), dtype=wp.vec3, device=dev)
        _head_paths(model, P, Q, cand[:n], dev)
        _head_paths(model, Q, P, cand[n:2 * n], dev)
        wp.launch(mlp.straight_paths, (n, levels[0]), inputs=[P, Q], outputs=[cand[2 * n:]], device=dev)
        starts, ends = wp.empty(3 * n, dtype=wp.vec3, device=dev), wp.empty(3 * n, dtype=wp.vec3, device=dev)
        for c, (a, b) in enumerate(((P, Q), (Q, P), (P, Q))):
            wp.copy(starts, a, dest_offset=c * n, count=n)
            wp.copy(ends, b, dest_offset=c * n, count=n)
        for level, ml in enumerate(levels):
            if level:
                finer = wp.empty((3 * n, ml), dtype=wp.vec3, device=dev)
                wp.launch(mlp.resample_paths, finer.shape, inputs=[cand], outputs=[finer], device=dev)
                cand = finer
            wp.launch(mlp.pin_and_project, cand.shape, inputs=[w, starts, ends, frame, PROJECT_STEPS],
                      outputs=[cand], device=dev)
            tmp = wp.empty_like(cand)
            for _ in range(int(refine)):
                wp.launch(mlp.relax_paths, cand.shape, inputs=[w, cand, frame, 1], outputs=[tmp], device=dev)
                cand, tmp = tmp, cand
        # a sweep takes one Newton step from the midpoint; at a crease the chord's midpoint lies deeper than
        # one step reaches, so the result gets a full projection
        wp.launch(mlp.pin_and_project, cand.shape, inputs=[w, starts, ends, frame, 2 * PROJECT_STEPS],
                  outputs=[cand], device=dev)
        rev = wp.array([0, 1, 0], dtype=wp.int32, device=dev)
        wp.launch(mlp.pick_shortest, (n, m), inputs=[cand, 3, rev], outputs=[res], device=dev)
    if kind == "torch":
        return wp.to_torch(res).view(n, m, 3)
    return out.result(res)


def _levels(m: int) -> list:
    """Point counts of the coarse-to-fine refinement: m/4, m/2, m (none under 8). Jacobi sweeps straighten a
    chain of k points in ~k^2 sweeps; the coarse levels do the long-range part cheaply."""
    out = [m]
    while len(out) < 3 and out[0] // 2 >= 8:
        out.insert(0, out[0] // 2)
    return out


def _head_paths(model: Model, P: wp.array, Q: wp.array, res: wp.array, dev):
    """The path head's points into res (N, m)."""
    n = P.shape[0]
    w = warp_weights(model, dev)
    e = wp.empty((2 * n, model.D), dtype=wp.float32, device=dev)
    frame = _frame(model)
    wp.launch(mlp.embed_points, n, inputs=[w, P, frame], outputs=[e[:n]], device=dev)
    wp.launch(mlp.embed_points, n, inputs=[w, Q, frame], outputs=[e[n:]], device=dev)
    g = wp.empty((n, model.D), dtype=wp.float32, device=dev)
    pre = wp.empty((n, w.p0_w.shape[0]), dtype=wp.float32, device=dev)
    wp.launch(mlp.path_guidance, (n, model.D), inputs=[w, e, n], outputs=[g], device=dev)
    wp.launch(mlp.path_first_layer, pre.shape, inputs=[w, g], outputs=[pre], device=dev)
    wp.launch(mlp.path_points, res.shape, inputs=[w, P, Q, pre, frame], outputs=[res], device=dev)


PROJECT_STEPS = 2  # Newton steps from a point near the surface; |sdf| falls ~10x per step (a trained SDF head)


def project(model: Model, x, steps: int = PROJECT_STEPS, device=None):
    """Points moved onto the surface of the network's SDF head (Newton steps on its zero level set): (N, 3) -> (N, 3)."""
    if not isinstance(steps, (int, np.integer)) or steps < 0:
        raise ValueError(f"steps must be an integer >= 0, got {steps!r}")
    dev = resolve_device(device, like=x)
    X, kind = as_points(x, "x", dev)
    out = Output(kind, dev)
    res = out.empty(X.shape[0], dtype=wp.vec3)
    wp.launch(mlp.project_points, X.shape[0], inputs=[warp_weights(model, dev), X, _frame(model), int(steps)],
              outputs=[res], device=dev)
    if kind == "torch":
        return wp.to_torch(res).view(-1, 3)
    return out.result(res)
