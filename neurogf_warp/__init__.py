"""neurogf_warp: neural geodesic fields with NVIDIA Warp."""
from .mesh import Mesh, load_mesh

__version__ = "0.1.0"
