"""The bundled default mesh: a smooth, closed, star-shaped blob generated on the fly (no file in the repo)."""
from __future__ import annotations

import numpy as np


def default_mesh(subdivisions: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """(vertices, faces) of an icosphere pushed out along its radii by a smooth bump field.

    Positive radii keep it free of self-intersections; the bumps and the stretch make geodesics bend, so the
    distance field is not just a rescaled sphere's. subdivisions=4 gives 2,562 vertices.
    """
    import trimesh

    s = trimesh.creation.icosphere(subdivisions=subdivisions)
    u = np.asarray(s.vertices, dtype=np.float64)
    x, y, z = u.T
    r = 1.0 + 0.22 * np.sin(3 * x + 1) * np.cos(2 * y) + 0.12 * np.sin(4 * z + 2 * x)
    v = u * r[:, None] * np.array([1.5, 1.0, 0.8])
    return v, np.asarray(s.faces, dtype=np.int64)
