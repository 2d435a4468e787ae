"""neurogf_warp: neural geodesic fields (NeuroGF) with NVIDIA Warp.

The pipeline, one module each: mesh -> geodesics (ground truth) -> dataset -> training -> inference.

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
    "Mesh": "mesh", "load_mesh": "mesh",
    "Model": "model",
    "load": "model_io", "load_querier": "model_io", "save": "model_io",
    "MeshMismatchWarning": "checkpoint_match",
    "ssad": "inference", "msad": "inference", "distance_matrix": "inference", "distance": "inference",
    "sdf": "inference", "path": "inference", "project": "inference", "embed": "inference", "warmup": "inference",
    "warp_weights": "inference",
    "geodesic_distances": "geodesics", "geodesic_paths": "geodesics",
    "Dataset": "dataset", "DatasetSettings": "dataset", "build_dataset": "dataset", "load_dataset": "dataset",
    "sdf_truth": "dataset",
    "train": "training", "TrainConfig": "training", "preset": "training", "TrainingInterrupted": "training",
    "evaluate": "evaluate",
    "render": "rendering", "write_ply": "rendering",
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
    from .checkpoint_match import MeshMismatchWarning
    from .dataset import Dataset, DatasetSettings, build_dataset, load_dataset, sdf_truth
    from .evaluate import evaluate
    from .geodesics import geodesic_distances, geodesic_paths
    from .inference import (distance, distance_matrix, embed, msad, path, project, sdf, ssad, warmup,
                            warp_weights)
    from .mesh import Mesh, load_mesh
    from .model import Model
    from .model_io import load, load_querier, save
    from .rendering import render, write_ply
    from .training import TrainConfig, TrainingInterrupted, preset, train
