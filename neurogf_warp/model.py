"""A trained NeuroGF: the torch network plus the frame it answers in.

With a mesh, queries take and return the mesh's own coordinates and units, and vertex indices follow the
mesh as given. Without one, everything is in the normalized unit-sphere frame the network was trained in.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .mesh import Mesh
from .network import NeuroGFNet, SdfQuerier

__all__ = ["Model"]


@dataclass(eq=False)
class Model:
    net: NeuroGFNet
    querier: SdfQuerier | None = None
    mesh: Mesh | None = None
    center: np.ndarray = field(default_factory=lambda: np.zeros(3))
    scale: float = 1.0
    config: dict = field(default_factory=dict)
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
        """True when inputs/outputs are in the mesh's coordinates (a mesh is attached)."""
        return self.mesh is not None

    def warp_struct(self, device=None):
        """The folded weights as a ``neurogf_warp.kernels.mlp.NeuroGFWeights`` struct on ``device``, for the
        ``@wp.func``s that users call inside their own kernels (cached; see ``invalidate``)."""
        from .inference import warp_weights

        return warp_weights(self, device)

    def invalidate(self):
        """Forget cached Warp weights, e.g. after changing ``net`` in place."""
        self._warp.clear()

    def __repr__(self):
        m = f"mesh with {self.mesh.n_input} vertices" if self.mesh is not None else "no mesh (normalized frame)"
        return f"Model(D={self.D}, {m}, querier={'yes' if self.querier is not None else 'no'})"
