"""Triangle meshes as NeuroGF sees them: referenced (optionally welded) vertices, plus the unit-sphere frame.

Users keep their own coordinates and vertex numbering: the file's own vertex records in file order
(``mesh_files``), or the arrays as given; ``Mesh.vertices``, ``faces`` and ``components`` are in that numbering.
Internally (``Mesh.internal_*``) we drop vertices no face uses, weld STL and other triangle soups (exact duplicate
coordinates), and work in the normalized frame the released models use: centre = bounding-box centre, scale so
that the largest vertex norm is 1. ``Mesh.input_to_internal`` maps every input vertex to its internal vertex, so
per-vertex results go back to the input numbering.
"""
from __future__ import annotations

import hashlib
import os
from dataclasses import dataclass, field

import numpy as np

from neurogf_warp.common.checks import InputError

__all__ = ["Mesh", "load_mesh", "mesh_fingerprint", "component_labels", "check_scale", "MIN_RADIUS", "MAX_RADIUS",
           "MAX_COORDINATE"]


def mesh_fingerprint(vertices: np.ndarray, faces: np.ndarray) -> str:
    """SHA-256 of a mesh (vertices as float32, faces as int64, little-endian): identifies a model's mesh.

    ``Mesh.fingerprint`` is this hash of the internal mesh (``internal_vertices``, ``internal_faces``: used vertices
    in input order, welded where the mesh was welded), so the same surface read from files that differ only in unused vertices has one
    fingerprint, and a stored mesh's fingerprint can be recomputed from it.
    """
    h = hashlib.sha256()
    h.update(np.ascontiguousarray(vertices, dtype="<f4").tobytes())
    h.update(np.ascontiguousarray(faces, dtype="<i8").tobytes())
    return h.hexdigest()


@dataclass(eq=False)
class Mesh:
    """A cleaned triangle mesh and the map back to the vertices as given.

    Two numberings: the **file's** (the vertex records as given, ``n_input`` of them), which is the only one the
    public surface uses (``vertices``, ``faces``, ``components``, every per-vertex result and argument), and the
    **internal** one (the vertices some face uses, welded where the input was welded, in input order), which
    the kernels use; every name in the internal numbering starts with ``internal_``.

    Attributes
    ----------
    vertices : (n_input, 3) float64, input units (read only)
        The position of every input vertex, in the file's order; NaN rows for vertices no face uses (they are
        not on the surface: their distances are NaN too). ``vertices[j]`` is the vertex of ``ssad(...)[j]``.
    faces : (F, 3) int64 (read only)
        The triangles, indexing ``vertices`` (file numbering); in a welded mesh a corner names the first of
        the input vertices welded together (they share one position).
    components : (n_input,) int32 (read only)
        Connected-component label of every input vertex, -1 for vertices no face uses.
    internal_vertices : (V, 3) float64, input units
        The internal vertices: those some face uses, welded where the input was welded, in input order.
    internal_faces : (F, 3) int32
        Triangles indexing ``internal_vertices``.
    index : (V,) int64
        One input vertex per internal vertex (the first of those welded into it), strictly increasing.
    n_input : int
        Number of vertices as given (the file's vertex records, or the rows of the vertex array).
    center : (3,) float64, input units; scale : float, 1 / input units
        ``normalized = (x - center) * scale`` puts the mesh in the unit sphere.
    fingerprint : str
        ``mesh_fingerprint(internal_vertices, internal_faces)``.
    """

    internal_vertices: np.ndarray
    internal_faces: np.ndarray
    index: np.ndarray
    n_input: int
    center: np.ndarray
    scale: float
    fingerprint: str
    _inverse: np.ndarray | None = field(default=None, repr=False)
    _components: np.ndarray | None = field(default=None, repr=False)
    _v1_fingerprint: str | None = field(default=None, repr=False)
    # the file-order views, made on first use (init=False: dataclasses.replace starts them afresh)
    _file_vertices: np.ndarray | None = field(default=None, init=False, repr=False)
    _file_faces: np.ndarray | None = field(default=None, init=False, repr=False)

    @property
    def vertices(self) -> np.ndarray:
        if self._file_vertices is None:
            out = np.full((self.n_input, 3), np.nan)
            used = self.input_to_internal >= 0
            out[used] = self.internal_vertices[self.input_to_internal[used]]
            out.flags.writeable = False  # derived: writing to it would change nothing the mesh uses
            self._file_vertices = out
        return self._file_vertices

    @property
    def faces(self) -> np.ndarray:
        if self._file_faces is None:
            out = self.index[self.internal_faces]
            out.flags.writeable = False
            self._file_faces = out
        return self._file_faces

    @property
    def components(self) -> np.ndarray:
        return self.to_input(self.internal_components, fill=-1)

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
    def welded(self) -> bool:
        """True when some internal vertex stands for several input vertices."""
        return int(np.count_nonzero(self.input_to_internal >= 0)) > len(self.internal_vertices)

    @property
    def internal_components(self) -> np.ndarray:
        """(V,) int32 connected-component label of each internal vertex (0 .. n_components - 1).

        Two vertices share a label when mesh edges join them; faces that meet only at a vertex are joined
        through it, as a geodesic can pass there. Across labels the geodesic distance is infinite. Labels
        are numbered in order of each component's first vertex.
        """
        if self._components is None:
            self._components = component_labels(len(self.internal_vertices), self.internal_faces)
        return self._components

    @property
    def n_components(self) -> int:
        return int(self.internal_components.max()) + 1 if len(self.internal_vertices) else 0

    @property
    def internal_normalized_vertices(self) -> np.ndarray:
        """(V, 3) float64: ``internal_vertices`` in the unit-sphere frame."""
        return (self.internal_vertices - self.center) * self.scale

    def normalize(self, x: np.ndarray) -> np.ndarray:
        return (np.asarray(x, dtype=np.float64) - self.center) * self.scale

    def denormalize(self, x: np.ndarray) -> np.ndarray:
        return np.asarray(x, dtype=np.float64) / self.scale + self.center

    def vertex(self, i) -> np.ndarray:
        """Internal vertex of each input vertex index.

        Parameters
        ----------
        i : int or (...,) int array
            Vertex indices in the input numbering, 0 .. n_input - 1.

        Returns
        -------
        (...,) int64 internal indices, the shape of ``i``.

        Raises
        ------
        TypeError for non-integer indices; IndexError for negative or out-of-range indices and for vertices
        no face uses (they have no geodesic distance).
        """
        i = np.asarray(i)
        if not np.issubdtype(i.dtype, np.integer):
            raise TypeError(f"vertex indices must be integers, got dtype {i.dtype}")
        if i.size and i.min() < 0:
            raise IndexError(f"vertex index {int(i.min())} is negative: vertex indices count from 0 to "
                             f"{self.n_input - 1} in the mesh's own numbering")
        if i.size and i.max() >= self.n_input:
            raise IndexError(f"vertex index {int(i.max())} is out of range for a mesh of {self.n_input} vertices "
                             f"(0 .. {self.n_input - 1})")
        j = self.input_to_internal[i]
        if np.any(j < 0):
            bad = i.ravel()[np.asarray(j).ravel() < 0][0]
            raise IndexError(f"vertex {int(bad)} is not used by any face, so it has no geodesic distance")
        return j

    def to_input(self, values: np.ndarray, fill=np.nan) -> np.ndarray:
        """Per-vertex values in the input numbering.

        Parameters
        ----------
        values : (..., V) array
            One value per internal vertex along the last axis.
        fill : scalar
            Value for input vertices no face uses.

        Returns
        -------
        (..., n_input) array of ``values``' dtype; welded input vertices share their internal vertex's value.
        """
        values = np.asarray(values)
        if values.shape[-1:] != (len(self.internal_vertices),):
            raise InputError(f"values must have one entry per internal vertex ({len(self.internal_vertices)}) on "
                             f"the last axis, got shape {values.shape}")
        inv = self.input_to_internal
        out = np.full(values.shape[:-1] + (self.n_input,), fill, dtype=values.dtype)
        used = inv >= 0
        out[..., used] = values[..., inv[used]]
        return out

    def to_trimesh(self):
        """A ``trimesh.Trimesh`` of the surface: the internal vertices and faces (no unused vertices)."""
        import trimesh

        return trimesh.Trimesh(self.internal_vertices, self.internal_faces, process=False)


# The supported sizes. The kernels work in float32, in the unit sphere, and give results in mesh units: outside
# these bounds distances (and squared lengths along paths) underflow to 0 or overflow to inf.
MIN_RADIUS = 1e-20
MAX_RADIUS = 1e30
MAX_COORDINATE = 1e32


def check_scale(radius: float, largest: float, pre: str = "") -> None:
    """Refuse a mesh whose size or coordinates float32 cannot carry through the normalized computations.

    Parameters
    ----------
    radius : float, input units
        The largest distance of a used vertex from the bounding-box centre.
    largest : float, input units
        The largest absolute vertex coordinate.
    pre : str
        Prefix of the message (e.g. the file name).

    Raises
    ------
    InputError
        ``radius`` outside [MIN_RADIUS, MAX_RADIUS] or ``largest`` above MAX_COORDINATE.
    """
    if not largest <= MAX_COORDINATE and radius <= MAX_RADIUS:
        raise InputError(f"{pre}the mesh's coordinates reach {largest:.3g}, beyond the supported {MAX_COORDINATE:g} "
                         "(float32 could not hold them); move the mesh nearer the origin or rescale it")
    if not MIN_RADIUS <= radius <= MAX_RADIUS:
        raise InputError(f"{pre}the mesh's size is outside the supported range: its bounding radius is {radius:.3g} "
                         f"units, and meshes from {MIN_RADIUS:g} to {MAX_RADIUS:g} units are supported (the "
                         "float32 computations would give distances of 0 or inf); rescale the mesh, e.g. by "
                         "expressing it in other units, and scale the results back")
    if not largest <= MAX_COORDINATE:
        raise InputError(f"{pre}the mesh's coordinates reach {largest:.3g}, beyond the supported {MAX_COORDINATE:g} "
                         "(float32 could not hold them); move the mesh nearer the origin or rescale it")


def _canonical_labels(labels: np.ndarray) -> np.ndarray:
    """Component labels renumbered 0, 1, ... in order of each component's first vertex."""
    labels = np.asarray(labels, dtype=np.int64)
    if labels.size == 0:
        return labels.astype(np.int32)
    _, first, inv = np.unique(labels, return_index=True, return_inverse=True)
    rank = np.empty(len(first), dtype=np.int64)
    rank[np.argsort(first, kind="stable")] = np.arange(len(first))
    return rank[inv.reshape(-1)].astype(np.int32)


def component_labels(n_vertices: int, faces: np.ndarray) -> np.ndarray:
    """(n_vertices,) int32 edge-connected component labels, numbered in order of each component's first vertex.

    Parameters
    ----------
    n_vertices : int
        Number of vertices.
    faces : (F, 3) int
        Triangles; vertices no face uses get a component of their own.
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    f = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    a = np.concatenate([f[:, 0], f[:, 1], f[:, 2]])
    b = np.concatenate([f[:, 1], f[:, 2], f[:, 0]])
    g = coo_matrix((np.ones(len(a), dtype=np.int8), (a, b)), shape=(n_vertices, n_vertices))
    _, labels = connected_components(g, directed=False)
    return _canonical_labels(labels)


def _is_soup(faces: np.ndarray) -> bool:
    """True when no vertex is shared by two face corners (every triangle has its own vertices)."""
    return len(faces) > 1 and int(np.bincount(faces.ravel()).max()) == 1


def _weld(v: np.ndarray, used: np.ndarray):
    """Merge used input vertices with identical coordinates.

    Returns the representative input vertex of each welded vertex (its first occurrence, so welded vertices
    keep the input order) and the welded vertex of each used input vertex.
    """
    # + 0.0 turns -0.0 into 0.0, so the two zeros count as the same coordinate
    _, first, inv = np.unique(v[used] + 0.0, axis=0, return_index=True, return_inverse=True)
    order = np.argsort(first, kind="stable")
    rank = np.empty(len(order), dtype=np.int64)
    rank[order] = np.arange(len(order))
    return used[first[order]], rank[inv.reshape(-1)]


def _from_arrays(vertices, faces, weld="auto", where: str = "") -> Mesh:
    """Build a Mesh from vertex records and triangles as given; ``where`` prefixes errors (e.g. a file name)."""
    pre = f"{where}: " if where else ""
    try:
        v, f = np.asarray(vertices), np.asarray(faces)
    except ValueError:  # ragged lists
        raise InputError(f"{pre}vertices and faces must be arrays of equal-length rows: (V, 3) vertex coordinates "
                         "and (F, 3) vertex indices") from None
    if v.dtype == object or f.dtype == object:
        raise TypeError(f"{pre}vertices and faces must be numeric arrays, got dtypes {v.dtype} and {f.dtype}")
    if not (np.issubdtype(v.dtype, np.floating) or np.issubdtype(v.dtype, np.integer)):
        raise TypeError(f"{pre}vertices must be numbers, got dtype {v.dtype}")
    v = v.astype(np.float64, copy=False)
    if v.ndim != 2 or v.shape[1] != 3:
        raise InputError(f"{pre}vertices must have shape (V, 3), got {v.shape}")
    if f.ndim != 2 or f.shape[1] != 3:
        raise InputError(f"{pre}faces must be triangles with shape (F, 3), got {f.shape}; triangulate the mesh first")
    if len(f) == 0:
        raise InputError(f"{pre}the mesh has no faces: NeuroGF needs a triangle surface")
    if not np.issubdtype(f.dtype, np.integer):
        raise TypeError(f"{pre}faces must be integer indices, got dtype {f.dtype}")
    if f.min() < 0 or f.max() >= len(v):
        raise InputError(f"{pre}face indices must lie in [0, {len(v)}), found {f.min()}..{f.max()}")
    if weld not in ("auto", True, False):
        raise InputError(f"weld must be 'auto', True or False, got {weld!r}")
    f = f.astype(np.int64, copy=False)
    used = np.flatnonzero(np.bincount(f.ravel(), minlength=len(v)))  # np.unique(f), in O(V + F) (a sort)
    if not np.all(np.isfinite(v[used])):
        raise InputError(f"{pre}the mesh has non-finite vertex coordinates (NaN or inf); clean the file first")
    if weld == "auto":
        weld = _is_soup(f)
    if weld:
        index, welded = _weld(v, used)
    else:
        index, welded = used, np.arange(len(used))
    inverse = np.full(len(v), -1, dtype=np.int64)
    inverse[used] = welded
    verts = v[index]
    tris = inverse[f].astype(np.int32)
    lo, hi = verts.min(0), verts.max(0)
    center = (lo + hi) / 2.0
    rel = verts - center
    with np.errstate(over="ignore", under="ignore"):
        radius = np.linalg.norm(rel, axis=1).max()
    size = float(np.abs(rel).max())
    if size > 0 and not (np.isfinite(radius) and radius > 0):  # squares overflowed (1e300) or underflowed (1e-200)
        radius = size * float(np.linalg.norm(rel / size, axis=1).max())
    if not radius > 0:
        raise InputError(f"{pre}the mesh is degenerate: all referenced vertices coincide")
    check_scale(radius, float(np.abs(verts).max()), pre)
    fp = mesh_fingerprint(verts, tris)
    # format-1 model files stored the fingerprint of the arrays as given; keep it to recognise them
    v1 = mesh_fingerprint(v, f) if (len(index) != len(v) and len(index) == len(used)) else fp
    return Mesh(internal_vertices=verts, internal_faces=tris, index=index.astype(np.int64), n_input=len(v),
                center=center,
                scale=float(1.0 / radius), fingerprint=fp, _inverse=inverse, _v1_fingerprint=v1)


def load_mesh(mesh, weld="auto") -> Mesh:
    """Load a triangle mesh, keeping the vertex numbering of the file or arrays it comes from.

    Parameters
    ----------
    mesh : str, os.PathLike, trimesh.Trimesh, (vertices, faces) or Mesh
        A mesh file (``.obj``, ``.ply`` and ``.stl`` are read record by record in file order; other formats
        through ``trimesh.load(..., process=False)``), an object with ``vertices`` and ``faces``, a pair of
        arrays ``vertices (n, 3)`` (units are yours) and ``faces (F, 3)`` int, or a Mesh (returned as is).
    weld : {"auto", True, False}
        Merge vertices whose float coordinates are exactly equal (after reading; -0.0 equals 0.0). Welding
        changes only the internal mesh: ``input_to_internal`` maps every input vertex to its welded vertex,
        so per-vertex results still come back one per input vertex. ``"auto"`` (default) welds STL files and
        triangle soups (input where no vertex is shared by two triangles, as STL exporters write), and keeps
        the topology of any other input as given, duplicate coordinates included. True always welds,
        False never does.

    Returns
    -------
    Mesh
        ``n_input`` is the number of vertex records given; vertices no face uses map to -1.

    Raises
    ------
    FileNotFoundError
        For a path that is not a file.
    ValueError, TypeError
        For input that is not a usable triangle mesh; messages name the file and the problem.
    """
    if isinstance(mesh, Mesh):
        return mesh
    if isinstance(mesh, (tuple, list)) and len(mesh) == 2:
        return _from_arrays(*mesh, weld=weld)
    if isinstance(mesh, (str, os.PathLike)):
        from neurogf_warp.mesh.files import read_mesh_file

        path = os.fspath(mesh)
        v, f, kind = read_mesh_file(path)
        return _from_arrays(v, f, weld=True if (weld == "auto" and kind == "stl") else weld, where=f"mesh file {path}")
    if hasattr(mesh, "vertices") and hasattr(mesh, "faces"):
        return _from_arrays(mesh.vertices, mesh.faces, weld=weld)
    raise TypeError(f"cannot make a mesh from {type(mesh).__name__}: give a path, a trimesh.Trimesh or (V, F)")
