"""Generalizable NeuroGF: one network for a whole family of shapes, conditioned on a point cloud, no training per shape.

    import neurogf_warp.generalizable as gen
    model = gen.load("GenNeuroGF.pth")          # the authors' released network, or a file written by gen.train
    cond = model.condition("mesh.obj")           # or an (N, 3) point cloud; ~ms on a GPU
    d = cond.distance(p, q); row = cond.ssad(0); D = cond.distance_matrix([0, 1, 2]); m = cond.msad([0, 9])

Modules: ``network`` (torch definition, strict loading, BN folding), ``encoder`` (Warp inference),
``model`` (the conditioned object), ``shapes`` (a shape-family collection), ``train`` (collection training,
torch.distributed). Names load lazily (torch and Warp are imported by the first function that needs them).
"""
from __future__ import annotations

from neurogf_warp.common.lazy import lazy_exports

_EXPORTS = {
    "load": "model", "GeneralizableModel": "model", "Conditioned": "model",
    "GenNeuroGF": "network", "load_network": "network", "is_generalizable_state_dict": "network",
    "is_generalizable_file": "network",
    "WarpGenNet": "encoder",
    "make_shape": "shapes", "write_collection": "shapes", "FAMILIES": "shapes",
    "train_generalizable": "train", "GenTrainConfig": "train",
}
__all__ = list(_EXPORTS)


__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS, globals())
