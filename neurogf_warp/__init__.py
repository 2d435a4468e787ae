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

import importlib
from typing import TYPE_CHECKING

__version__ = "0.1.0"

# public name -> module that defines it
_EXPORTS = {
    "Mesh": "mesh.mesh", "load_mesh": "mesh.mesh",
    "Model": "model.model",
    "load": "model.files", "load_querier": "model.files", "save": "model.files",
    "MeshMismatchWarning": "model.checkpoint_match",
    **{name: "inference.queries" for name in ("ssad", "msad", "distance_matrix", "distance", "sdf", "path", "project",
                                              "embed", "warmup", "warp_weights", "bind", "unbind")},
    "geodesic_distances": "ground_truth.geodesics", "geodesic_paths": "ground_truth.geodesics",
    **{name: "dataset.build" for name in ("Dataset", "DatasetSettings", "build_dataset", "load_dataset", "sdf_truth")},
    "train": "training", "TrainConfig": "training", "preset": "training", "TrainingInterrupted": "training",
    "evaluate": "evaluation.evaluate",
    "render": "pictures.render", "write_ply": "pictures.render",
}

__all__ = list(_EXPORTS) + ["__version__"]


def __getattr__(name: str):
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module 'neurogf_warp' has no attribute {name!r}")
    value = getattr(importlib.import_module(f".{module}", __name__), name)
    globals()[name] = value
    return value


def __dir__():
    return sorted(set(globals()) | set(_EXPORTS))


if TYPE_CHECKING:  # for type checkers and IDEs; at run time the names load lazily above
    from neurogf_warp.dataset.build import Dataset, DatasetSettings, build_dataset, load_dataset, sdf_truth
    from neurogf_warp.evaluation.evaluate import evaluate
    from neurogf_warp.ground_truth.geodesics import geodesic_distances, geodesic_paths
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
    from neurogf_warp.mesh.mesh import Mesh, load_mesh
    from neurogf_warp.model.checkpoint_match import MeshMismatchWarning
    from neurogf_warp.model.files import load, load_querier, save
    from neurogf_warp.model.model import Model
    from neurogf_warp.pictures.render import render, write_ply
    from neurogf_warp.training import TrainConfig, TrainingInterrupted, preset, train
