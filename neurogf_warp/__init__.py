"""neurogf_warp: neural geodesic fields (NeuroGF) with NVIDIA Warp.

The pipeline, one subpackage a stage: mesh -> ground_truth -> dataset -> (model) -> training -> inference,
then evaluation, pictures and the command line (cli).

    import neurogf_warp as ngf
    model = ngf.load("bunny.ngf")          # or a released *_final.pth with mesh=...
    d = ngf.ssad(model, 0)                 # distance from vertex 0 to every vertex

Names are imported on first use, so ``import neurogf_warp`` (and the command line's ``--help``) stays fast;
torch and Warp load with the first function that needs them.
"""
from __future__ import annotations

from typing import TYPE_CHECKING

from neurogf_warp.common.lazy import lazy_exports

__version__ = "0.1.0"

# public name -> module that defines it
_EXPORTS = {
    "Mesh": "mesh.mesh", "load_mesh": "mesh.mesh",
    "Model": "model.model",
    "load_querier": "model.files", "save": "model.files",
    "MeshMismatchWarning": "model.checkpoint_match",
    **{name: "inference.queries" for name in ("ssad", "msad", "distance_matrix", "distance", "sdf", "path", "project",
                                              "embed", "warmup", "warp_weights", "bind", "unbind")},
    "geodesic_distances": "ground_truth.geodesics", "geodesic_paths": "ground_truth.geodesics",
    "clear_solver_cache": "ground_truth.geodesics",
    **{name: "dataset.build" for name in ("Dataset", "DatasetSettings", "build_dataset", "load_dataset", "sdf_truth")},
    "train": "training", "ModelQualityWarning": "training", "TrainConfig": "training", "preset": "training", "TrainingInterrupted": "training",
    "evaluate": "evaluation.evaluate",
    "render": "pictures.render", "write_ply": "pictures.render",
    "reconstruct": "inference.reconstruct",
    **{name: "inference.sampling" for name in ("farthest_point_sampling", "voronoi", "nearest_seeds", "isolines")},
}

__all__ = list(_EXPORTS) + ["__version__", "load"]


def load(path, mesh=None, **kwargs):
    """Load a model file: a per-mesh model (``.ngf``, or a released ``*_final.pth`` with ``mesh``), or a
    generalizable network (the released ``GenNeuroGF.pth`` or a file of ``neurogf-warp gen-train``).

    A per-mesh file gives a ``Model`` (see ``neurogf_warp.model.files.load`` for ``querier`` and ``check_mesh``). A
    generalizable file gives a ``GeneralizableModel``, or with ``mesh`` (a mesh, a mesh file or a point cloud) the
    network already conditioned on it, which answers ``distance``, ``ssad``, ``msad`` and ``distance_matrix``.
    """
    # the dispatch lives at the package's top, above every stage: the model stage may not import the
    # generalizable one (tests/test_layers.py)
    import os

    from neurogf_warp.generalizable.hooks import load_if_generalizable

    # only a regular file is looked into here: opening a FIFO would block (the model loader says what it is)
    gen = load_if_generalizable(path, mesh) if os.path.isfile(path) else None
    if gen is not None:
        if kwargs:
            raise TypeError(f"a generalizable network takes no {', '.join(sorted(kwargs))}")
        return gen
    from neurogf_warp.model.files import load as load_model

    return load_model(path, mesh=mesh, **kwargs)


__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS, globals())


if TYPE_CHECKING:  # for type checkers and IDEs; at run time the names load lazily above
    from neurogf_warp.dataset.build import Dataset, DatasetSettings, build_dataset, load_dataset, sdf_truth
    from neurogf_warp.evaluation.evaluate import evaluate
    from neurogf_warp.ground_truth.geodesics import clear_solver_cache, geodesic_distances, geodesic_paths
    from neurogf_warp.inference.queries import (
        bind,
        distance,
        distance_matrix,
        embed,
        msad,
        path,
        project,
        sdf,
        ssad,
        unbind,
        warmup,
        warp_weights,
    )
    from neurogf_warp.inference.reconstruct import reconstruct
    from neurogf_warp.inference.sampling import farthest_point_sampling, isolines, nearest_seeds, voronoi
    from neurogf_warp.mesh.mesh import Mesh, load_mesh
    from neurogf_warp.model.checkpoint_match import MeshMismatchWarning
    from neurogf_warp.model.files import load_querier, save
    from neurogf_warp.model.model import Model
    from neurogf_warp.pictures.render import render, write_ply
    from neurogf_warp.training import ModelQualityWarning, TrainConfig, TrainingInterrupted, preset, train
