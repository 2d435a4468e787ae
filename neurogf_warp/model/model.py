"""A trained NeuroGF: the torch network plus the frame it answers in."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from neurogf_warp.mesh.mesh import Mesh
from neurogf_warp.model.network import NeuroGFNet, SdfQuerier

__all__ = ["Model"]


@dataclass(eq=False)
class Model:
    """A trained NeuroGF network and the frame it answers in.

    Attributes
    ----------
    net : network.NeuroGFNet
        The torch network (eval mode): lifting, distance, SDF and path heads.
    querier : network.SdfQuerier or None
        The separate SDF network used while training (optional).
    mesh : mesh.Mesh or None
        The mesh the network was fitted to. With it, queries take and return the mesh's own coordinates and
        units and per-vertex results follow the mesh file's numbering; without it, everything is in the
        normalized unit-sphere frame.
    center : (3,) float64, scale : float
        The normalization: network coordinates = (x - center) * scale.
    config : dict
        How the model was made (training settings, source file).
    mesh_frame : bool
        True when ``center``/``scale`` are a mesh's frame even without a mesh attached (a model file saved
        without its mesh keeps its normalization): queries then take and return mesh coordinates and units.

    Per-device state (folded weights, packed tensor-core weights, kept vertex embeddings) is cached in the
    model by the inference stage (``neurogf_warp.bind``, the queries); ``invalidate()`` drops it after the network
    is changed in place, ``unbind()`` frees the kept embeddings.
    """

    net: NeuroGFNet
    querier: SdfQuerier | None = None
    mesh: Mesh | None = None
    center: np.ndarray = field(default_factory=lambda: np.zeros(3))
    scale: float = 1.0
    config: dict = field(default_factory=dict)
    mesh_frame: bool = False
    _warp: dict = field(default_factory=dict, repr=False)  # device -> folded Warp weights

    def __post_init__(self):
        self.net.eval()
        if self.querier is not None:
            self.querier.eval()
        self.center = np.asarray(self.center, dtype=np.float64).reshape(3)
        self.scale = float(self.scale)

    @property
    def D(self) -> int:
        return self.net.D

    @property
    def in_mesh_frame(self) -> bool:
        """True when inputs/outputs are in the mesh's coordinates (a mesh is attached, or its frame was kept)."""
        return self.mesh is not None or self.mesh_frame

    def unbind(self, device=None) -> None:
        """Free the vertex embeddings kept on ``device`` (every device when None); see ``neurogf_warp.bind``."""
        dev = None if device is None else str(device)
        for key in [k for k in self._warp if isinstance(k, tuple) and k[0] in ("bound", "bound_tables")
                    and (dev is None or k[1] == dev)]:
            del self._warp[key]

    def invalidate(self):
        """Forget all cached per-device state (weights, embeddings), e.g. after changing ``net`` in place."""
        self._warp.clear()

    def __repr__(self):
        m = f"mesh with {self.mesh.n_input} vertices" if self.mesh is not None else "no mesh (normalized frame)"
        return f"Model(D={self.D}, {m}, querier={'yes' if self.querier is not None else 'no'})"
