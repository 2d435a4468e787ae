"""The heat method (potpourri3d, the optional ``heat`` extra): the baseline a trained model must beat.

Training compares its held-out validation error with the heat method's on the same pairs, and evaluation reports
both; both stages import it from here.
"""
from __future__ import annotations

import importlib.util

import numpy as np

__all__ = ["HEAT_HINT", "heat_available", "require_heat", "heat_distances"]

HEAT_HINT = 'the heat-method comparison needs potpourri3d: pip install "neurogf-warp[heat]"'


def heat_available() -> bool:
    """True when potpourri3d can be imported."""
    return importlib.util.find_spec("potpourri3d") is not None


def require_heat() -> None:
    """Raise ImportError (naming the ``heat`` extra) when potpourri3d is not installed."""
    if not heat_available():
        raise ImportError(HEAT_HINT)


def heat_distances(vertices, faces, sources, on_row=None) -> np.ndarray:
    """Heat-method geodesic distances (potpourri3d's defaults) from each source vertex to every vertex.

    vertices : (V, 3) float, faces : (F, 3) int, sources : (S,) vertex ids; on_row() is called after each row.
    Returns (S, V) float64 in the units of ``vertices``.
    """
    require_heat()
    import potpourri3d as pp3d

    solver = pp3d.MeshHeatMethodDistanceSolver(np.asarray(vertices, np.float64), np.asarray(faces, np.int64))
    out = np.empty((len(sources), len(vertices)), np.float64)
    for i, s in enumerate(np.asarray(sources).reshape(-1)):
        out[i] = solver.compute_distance(int(s))
        if on_row is not None:
            on_row()
    return out
