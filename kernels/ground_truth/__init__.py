"""Warp kernels of the ground-truth geodesic solver (front: neurogf_warp.ground_truth.geodesics).

A Steiner-point graph (k points per edge) relaxed from many sources at once, where every node also carries one
unfolding window so that rays continue straight across faces (exact triangle unfolding). Every value is the
length of a real surface path, so distances are upper bounds of the exact geodesic distance.

- graph: the Steiner graph on the mesh (node ids, positions, face slots, edge frames), `SteinerGraph`;
- unfolding: windows and the unfolding maths, `Windows`;
- relax: the frontier-worklist relaxation (propose, decode, commit), `NodeState`, `PathRecords`, `Frontier`;
- paths: distances made equal to the traced paths' lengths, and the path tracer, `PathQuery`;
- build: the graph's per-node and per-slot tables written on the device.
"""
from . import build, graph, paths, relax, unfolding

MODULES = (relax, paths, build)  # the modules that hold kernels (graph and unfolding hold functions only)


def load(device) -> None:
    """Compile (or load from the kernel cache) every solver kernel for `device`, the modules in parallel threads
    (NVRTC and Warp's CPU compiler run outside the GIL)."""
    import warp as wp

    wp.force_load(device, modules=[wp.get_module(m.__name__) for m in MODULES], max_workers=len(MODULES))
