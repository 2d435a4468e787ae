"""neurogf_warp: neural geodesic fields (NeuroGF) with NVIDIA Warp.

    import neurogf_warp as ngf
    model = ngf.load("bunny.ngf")          # or a released *_final.pth with mesh=...
    d = ngf.ssad(model, 0)                 # distance from vertex 0 to every vertex
"""
from .inference import distance, embed, msad, path, sdf, ssad, warp_weights
from .mesh import Mesh, load_mesh
from .model import Model
from .model_io import load, load_querier, save

__version__ = "0.1.0"

__all__ = [
    "Mesh", "Model", "load_mesh", "load", "load_querier", "save",
    "ssad", "msad", "distance", "sdf", "path", "embed", "warp_weights",
]
