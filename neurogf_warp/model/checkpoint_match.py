"""Does a mesh look like the one a released checkpoint was trained on? The SDF head's value at its vertices.

A released ``*_final.pth`` stores no normalization and no mesh fingerprint: the normalization is computed
from the mesh the user passes. The network's SDF head has the training surface as its zero level set, so on
the right mesh, normalized the same way, ``|sdf|`` at the vertices is tiny; another mesh, or the right one
with parts added or cut off (which moves the bounding box and so the normalization), gives values two orders
of magnitude larger. One forward pass of the lifting and SDF head over a few hundred vertices decides it.
"""
from __future__ import annotations

import warnings

import numpy as np
import torch

from neurogf_warp.common.checks import InputError

__all__ = ["MeshMismatchWarning", "MeshMismatchError", "mesh_sdf_residual", "warn_if_mesh_mismatch", "MAX_MEAN_ABS_SDF"]

# Vertices looked at (evenly spaced through the vertex list).
SAMPLES = 512
# Mean |sdf| (normalized units: the mesh fits the unit sphere) above which a mesh is reported. Matching
# meshes give about 1e-3 or less (a remeshed copy of the same surface included); other shapes, and a mesh
# whose bounding box differs from the training mesh's by a few percent, 3e-2 and more.
MAX_MEAN_ABS_SDF = 1e-2


class MeshMismatchWarning(UserWarning):
    """A released checkpoint was loaded with a mesh that does not lie on its SDF zero level set.

    The Python API only warns (``load`` returns the model, whose every answer for that mesh is wrong); turn it
    into an error with ``warnings.simplefilter("error", MeshMismatchWarning)``. The command line refuses such a
    mesh (exit code 2) unless ``--allow-mesh-mismatch`` is given."""


class MeshMismatchError(InputError):
    """A model file was given a mesh other than the one it was trained on (fingerprints differ).

    ``problem`` says what is wrong without the remedy, so that the command line can name its own flag."""

    def __init__(self, problem: str, remedy: str):
        super().__init__(f"{problem}. {remedy}")
        self.problem = problem


def mesh_sdf_residual(model, samples: int = SAMPLES) -> float:
    """Mean |SDF head| at up to ``samples`` mesh vertices, in the normalized frame (unit-sphere units).

    Parameters
    ----------
    model : Model
        A model with a mesh attached.
    samples : int
        Number of vertices evaluated, evenly spaced through the mesh's vertex list.

    Returns
    -------
    float, normalized units (multiply by ``1 / model.scale`` for mesh units).
    """
    if model.mesh is None:
        raise InputError("mesh_sdf_residual needs a model with a mesh")
    x = (model.mesh.internal_vertices - model.center) * model.scale
    idx = np.unique(np.linspace(0, len(x) - 1, min(len(x), int(samples))).round().astype(np.int64))
    net = model.net
    p = next(net.parameters())
    with torch.no_grad():
        s = net.sdf(torch.as_tensor(x[idx], dtype=p.dtype, device=p.device))
    return float(s.abs().mean())


def warn_if_mesh_mismatch(model, path: str = "the checkpoint") -> float:
    """Warn (``MeshMismatchWarning``) when ``model.mesh`` does not look like the checkpoint's training mesh.

    Returns the mean |sdf| measured (normalized units).
    """
    r = mesh_sdf_residual(model)
    if not r <= MAX_MEAN_ABS_SDF:
        warnings.warn(
            f"{path}: the given mesh does not lie on this checkpoint's surface (mean |sdf| at its vertices "
            f"{r:.3g} in the unit-sphere frame; a matching mesh gives about 1e-3 or less). A released checkpoint "
            "stores no normalization, so it is computed from the mesh you pass: with another mesh, or one with "
            "parts added or removed, every answer is wrong. Pass the mesh the checkpoint was trained on.",
            MeshMismatchWarning, stacklevel=3)
    return r
