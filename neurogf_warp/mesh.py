"""Triangle meshes as NeuroGF sees them: referenced vertices only, plus the unit-sphere normalization.

Users keep their own coordinates and vertex numbering (file order, as trimesh loads it with
``process=False``). Internally we drop unreferenced vertices and work in the normalized frame the released
models use: centre = bounding-box centre, scale so the largest vertex norm is 1.
"""
from __future__ import annotations

import hashlib
import os
from dataclasses import dataclass, field

import numpy as np

__all__ = ["Mesh", "load_mesh", "mesh_fingerprint"]


def mesh_fingerprint(vertices: np.ndarray, faces: np.ndarray) -> str:
    """SHA-256 of the mesh as given (float32 vertices, int64 faces): identifies a model's mesh."""
    h = hashlib.sha256()
    h.update(np.ascontiguousarray(vertices, dtype="<f4").tobytes())
    h.update(np.ascontiguousarray(faces, dtype="<i8").tobytes())
    return h.hexdigest()


@dataclass(eq=False)
class Mesh:
    """A cleaned triangle mesh.

    vertices: (V, 3) float64, the referenced vertices in the user's coordinates.
    faces:    (F, 3) int32 indices into ``vertices``.
    index:    (V,) int64, position of each vertex among the vertices as given (``n_input`` of them).
    center, scale: normalized = (x - center) * scale puts the mesh in the unit sphere.
    """

    vertices: np.ndarray
    faces: np.ndarray
    index: np.ndarray
    n_input: int
    center: np.ndarray
    scale: float
    fingerprint: str
    _inverse: np.ndarray | None = field(default=None, repr=False)
    _components: np.ndarray | None = field(default=None, repr=False)

    @property
    def input_to_internal(self) -> np.ndarray:
        """(n_input,) int64: the internal vertex of each vertex as given, -1 where no face uses it.

        Several input vertices may share one internal vertex (a welded file); per-vertex results are
        gathered through this map, so every input vertex gets its internal vertex's value.
        """
        if self._inverse is None:
            inv = np.full(self.n_input, -1, dtype=np.int64)
            inv[self.index] = np.arange(len(self.index))
            self._inverse = inv
        return self._inverse

    @property
    def components(self) -> np.ndarray:
        """(V,) int32 connected-component label of each internal vertex (0 .. n_components - 1).

        Two vertices share a label when mesh edges join them; faces that meet only at a vertex are joined
        through it, as a geodesic can pass there. Across labels the geodesic distance is infinite.
        """
        if self._components is None:
            from scipy.sparse import coo_matrix
            from scipy.sparse.csgraph import connected_components

            f = self.faces.astype(np.int64)
            a = np.concatenate([f[:, 0], f[:, 1], f[:, 2]])
            b = np.concatenate([f[:, 1], f[:, 2], f[:, 0]])
            n = len(self.vertices)
            g = coo_matrix((np.ones(len(a), dtype=np.int8), (a, b)), shape=(n, n))
            _, labels = connected_components(g, directed=False)
            self._components = labels.astype(np.int32)
        return self._components

    @property
    def n_components(self) -> int:
        return int(self.components.max()) + 1 if len(self.vertices) else 0

    @property
    def normalized_vertices(self) -> np.ndarray:
        return (self.vertices - self.center) * self.scale

    def normalize(self, x: np.ndarray) -> np.ndarray:
        return (np.asarray(x, dtype=np.float64) - self.center) * self.scale

    def denormalize(self, x: np.ndarray) -> np.ndarray:
        return np.asarray(x, dtype=np.float64) / self.scale + self.center

    def vertex(self, i) -> np.ndarray:
        """Internal indices of the given (file-order) vertex indices; raises on out-of-range or unreferenced."""
        i = np.asarray(i)
        if not np.issubdtype(i.dtype, np.integer):
            raise TypeError(f"vertex indices must be integers, got dtype {i.dtype}")
        if i.size and (i.min() < -self.n_input or i.max() >= self.n_input):
            bad = i[(i < -self.n_input) | (i >= self.n_input)].ravel()[0]
            raise IndexError(f"vertex index {int(bad)} is out of range for a mesh of {self.n_input} vertices")
        j = self.input_to_internal[i % self.n_input]
        if np.any(j < 0):
            bad = np.asarray(i).ravel()[np.asarray(j).ravel() < 0][0]
            raise IndexError(f"vertex {int(bad)} is not used by any face, so it has no geodesic distance")
        return j

    def to_input(self, values: np.ndarray, fill=np.nan) -> np.ndarray:
        """Scatter per-vertex values (last axis = internal vertices) back to the vertices as given."""
        values = np.asarray(values)
        inv = self.input_to_internal
        out = np.full(values.shape[:-1] + (self.n_input,), fill, dtype=values.dtype)
        used = inv >= 0
        out[..., used] = values[..., inv[used]]
        return out

    def to_trimesh(self):
        import trimesh

        return trimesh.Trimesh(self.vertices, self.faces, process=False)


def _from_arrays(vertices, faces) -> Mesh:
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces)
    if v.ndim != 2 or v.shape[1] != 3:
        raise ValueError(f"vertices must have shape (V, 3), got {v.shape}")
    if f.ndim != 2 or f.shape[1] != 3:
        raise ValueError(f"faces must be triangles with shape (F, 3), got {f.shape}; triangulate the mesh first")
    if len(f) == 0:
        raise ValueError("the mesh has no faces: NeuroGF needs a triangle surface")
    if not np.issubdtype(f.dtype, np.integer):
        raise TypeError(f"faces must be integer indices, got dtype {f.dtype}")
    if f.min() < 0 or f.max() >= len(v):
        raise ValueError(f"face indices must lie in [0, {len(v)}), found {f.min()}..{f.max()}")
    used = np.unique(f)
    if not np.all(np.isfinite(v[used])):
        raise ValueError("the mesh has non-finite vertex coordinates (NaN or inf); clean the file first")
    remap = np.full(len(v), -1, dtype=np.int64)
    remap[used] = np.arange(len(used))
    verts = v[used]
    lo, hi = verts.min(0), verts.max(0)
    center = (lo + hi) / 2.0
    radius = np.linalg.norm(verts - center, axis=1).max()
    if not radius > 0:
        raise ValueError("the mesh is degenerate: all referenced vertices coincide")
    return Mesh(
        vertices=verts,
        faces=remap[f].astype(np.int32),
        index=used.astype(np.int64),
        n_input=len(v),
        center=center,
        scale=float(1.0 / radius),
        fingerprint=mesh_fingerprint(v, f),
    )


def load_mesh(mesh) -> Mesh:
    """Load a triangle mesh from a path, a trimesh.Trimesh, a (vertices, faces) pair, or pass a Mesh through."""
    if isinstance(mesh, Mesh):
        return mesh
    if isinstance(mesh, (tuple, list)) and len(mesh) == 2:
        return _from_arrays(*mesh)
    if isinstance(mesh, (str, os.PathLike)):
        import trimesh

        path = os.fspath(mesh)
        if not os.path.isfile(path):
            raise FileNotFoundError(f"mesh file not found: {path}")
        try:
            tm = trimesh.load(path, process=False, force="mesh")
        except Exception as e:  # trimesh raises many types for bad files
            raise ValueError(f"could not read mesh file {path}: {e}") from e
        if not hasattr(tm, "faces") or len(getattr(tm, "faces", [])) == 0:
            raise ValueError(f"mesh file {path} has no triangle faces")
        return _from_arrays(tm.vertices, tm.faces)
    if hasattr(mesh, "vertices") and hasattr(mesh, "faces"):
        return _from_arrays(mesh.vertices, mesh.faces)
    raise TypeError(f"cannot make a mesh from {type(mesh).__name__}: give a path, a trimesh.Trimesh or (V, F)")
