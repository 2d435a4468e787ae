"""The Warp structs a user's kernel takes from a model: folded weights, the coordinate frame, a source set.

    import neurogf_warp as ngf
    from neurogf_warp.kernels import field
    from neurogf_warp.inference.warp_structs import frame, source_set

    net = weights(model, "cuda:0")            # field.NeuroGFWeights
    fr = frame(model)                            # field.Frame: field.to_net(fr, x), distances * fr.dscale
    src = source_set(model, [0, 17], "cuda:0")   # field.SourceSet: MSAD sources, bound once
    lm = landmarks(model, "cuda:0")              # field.LandmarkTable of a landmark network (network frame)

Keep the model alive while kernels use these structs: they point into arrays the model caches.
"""
from __future__ import annotations

import numpy as np
import warp as wp

from neurogf_warp.common.arrays import resolve_device
from neurogf_warp.inference.queries import embed
from neurogf_warp.inference.state import query_state
from neurogf_warp.kernels import field
from neurogf_warp.kernels.inference import mlp
from neurogf_warp.mesh.surface import points_of

__all__ = ["weights", "frame", "source_set", "landmarks"]


def weights(model, device=None) -> mlp.NeuroGFWeights:
    """The model's folded float32 weights on ``device`` (kept by the model's per-device state)."""
    return query_state(model, device).weights


def frame(model) -> mlp.Frame:
    """Mesh coordinates -> network frame: ``mlp.to_net(f, x)`` (the centre is subtracted in float64, so float32
    points far from the origin keep their own resolution); network distances times ``f.dscale`` are in mesh
    units; ``mlp.from_net(f, y)`` maps network points back. The identity for a model without a mesh."""
    return query_state(model).user_frame


def source_set(model, sources, device=None) -> field.SourceSet:
    """The sources' embeddings and points (network frame) on ``device``, for ``field.distance_to_sources`` and
    friends.

    Parameters
    ----------
    model : Model
    sources : vertex indices (the mesh's own numbering) or (S, 3) float points, mesh units (normalized frame for
        a model without a mesh)
    device : Warp device (default: Warp's preferred one)
    """
    dev = resolve_device(device)
    pts = points_of(model.mesh, sources, "sources")
    if len(pts) == 0:
        raise ValueError("sources is empty: give at least one vertex index or point")
    s = field.SourceSet()
    st = query_state(model, dev)
    net_pts = (np.asarray(pts, np.float64) - st.center) * float(st.frame.xscale)  # float64, then float32
    s.points = wp.array(net_pts.astype(np.float32), dtype=wp.vec3, device=dev)
    s.emb = embed(model, pts, dev)
    return s


def landmarks(model, device=None) -> field.LandmarkTable:
    """A landmark network's table for ``field.locate`` and ``field.landmark_distance``: the exact distances of every
    mesh vertex to the landmarks (rows in the mesh's internal vertex order, normalized units), the vertices and a
    ``wp.Mesh`` of them in the network frame (``to_net(frame(model), x)``), on ``device``. Kept by the model's
    per-device state. Vertex rows for ``field.vertex_location`` are internal indices:
    ``model.mesh.input_to_internal[i]`` for the file's vertex i."""
    return query_state(model, device).kernel_landmarks()
