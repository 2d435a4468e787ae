"""neurogf_warp: neural geodesic fields (NeuroGF) with NVIDIA Warp.

The pipeline, one module each: mesh -> geodesics (ground truth) -> dataset -> train -> inference.

    import neurogf_warp as ngf
    model = ngf.load("bunny.ngf")          # or a released *_final.pth with mesh=...
    d = ngf.ssad(model, 0)                 # distance from vertex 0 to every vertex
"""
from .checkpoint_match import MeshMismatchWarning
from .dataset import build_dataset, load_dataset, sample_sdf_points, sdf_truth
from .evaluate import evaluate
from .geodesics import geodesic_distances, geodesic_paths
from .inference import distance, distance_matrix, embed, msad, path, project, sdf, ssad, warmup, warp_weights
from .mesh import Mesh, load_mesh
from .model import Model
from .model_io import load, load_querier, save
from .rendering import render, write_ply
from .train import train  # after the submodule import, so `neurogf_warp.train` is the function


__version__ = "0.1.0"

__all__ = [
    "Mesh", "Model", "load_mesh", "load", "load_querier", "save", "MeshMismatchWarning",
    "ssad", "msad", "distance_matrix", "distance", "sdf", "path", "project", "embed", "warmup", "warp_weights",
    "geodesic_distances", "geodesic_paths",
    "build_dataset", "load_dataset", "sdf_truth", "sample_sdf_points", "train", "evaluate", "render", "write_ply",
]
