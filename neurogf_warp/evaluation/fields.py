"""Reference fields and paths to draw beside a model's: the exact field of a reference file, and the heat method's
field with potpourri3d's edge-flip geodesic paths (the ``render --exact`` / ``--heat`` pictures).

Every function takes and returns the mesh file's vertex numbering and mesh units.
"""
from __future__ import annotations

import os

import numpy as np

from neurogf_warp.common.checks import InputError
from neurogf_warp.mesh.mesh import Mesh

__all__ = ["exact_field", "heat_field", "heat_paths"]


def exact_field(reference: "str | os.PathLike", mesh: Mesh, sources) -> np.ndarray:
    """Exact distance to the nearest of ``sources`` per vertex, read from a reference file.

    Parameters
    ----------
    reference : an exact-distance .npz (positions, orig_index or file_index, sources, dist), see
        ``evaluation.evaluate.load_reference``
    mesh : the reference's mesh
    sources : vertex indices in the mesh file's numbering; each must be one of the reference's sources

    Returns
    -------
    (mesh.n_input,) float64, mesh units; NaN at vertices the reference does not cover.
    """
    from neurogf_warp.evaluation.evaluate import load_reference

    vids, sids, dist = load_reference(reference, mesh)
    sources = [int(s) for s in np.asarray(sources).reshape(-1)]
    want = mesh.vertex(np.asarray(sources))
    rows = []
    for s, w in zip(sources, want):
        hit = np.flatnonzero(sids == w)
        if not len(hit):
            raise InputError(f"source {s} is not one of {reference}'s sources "
                             f"({', '.join(map(str, mesh.index[sids]))})")
        rows.append(dist[hit[0]])
    out = np.full(len(mesh.internal_vertices), np.nan)
    out[vids] = np.min(rows, axis=0)
    return mesh.to_input(out)


def heat_field(mesh: Mesh, sources) -> np.ndarray:
    """The heat method's distance (potpourri3d, its default time step) to the nearest of ``sources`` (vertex
    indices, the mesh file's numbering): (mesh.n_input,) float64, mesh units, NaN at unused vertices and inf on
    the parts of the mesh that hold no source (as the solver's and the model's fields)."""
    import potpourri3d as pp3d

    solver = pp3d.MeshHeatMethodDistanceSolver(mesh.internal_vertices, mesh.internal_faces.astype(np.int64))
    ids = mesh.vertex(np.asarray(sources).reshape(-1))
    d = np.asarray(solver.compute_distance_multisource([int(i) for i in ids]), dtype=np.float64)
    # the heat method's values on a part that no source reaches are numbers without meaning
    comp = mesh.components
    return mesh.to_input(np.where(np.isin(comp, comp[ids]), d, np.inf))


def heat_paths(mesh: Mesh, source: int, targets) -> list:
    """Geodesic paths from vertex ``source`` to each of ``targets`` (the mesh file's numbering) by potpourri3d's
    edge-flip solver: a list of (m_i, 3) float64 polylines, mesh units."""
    import potpourri3d as pp3d

    flip = pp3d.EdgeFlipGeodesicSolver(mesh.internal_vertices, mesh.internal_faces.astype(np.int64))
    s0 = int(mesh.vertex(np.asarray([int(source)]))[0])
    return [np.asarray(flip.find_geodesic_path(s0, int(t))) for t in mesh.vertex(np.asarray(targets).reshape(-1))]
