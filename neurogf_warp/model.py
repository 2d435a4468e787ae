"""A trained NeuroGF: the torch network plus the frame it answers in."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .mesh import Mesh
from .network import NeuroGFNet, SdfQuerier

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

    Per-device state (folded weights, packed tensor-core weights, kept vertex embeddings) is cached in the
    model; ``invalidate()`` drops it after the network is changed in place, ``unbind()`` frees the embeddings.
    """

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
        from .device_state import warp_weights

        return warp_weights(self, device)

    def bind(self, device=None, precision: str = "auto") -> int:
        """Embed every mesh vertex once and keep the embeddings on ``device``, so that vertex queries (ssad,
        msad, distance_matrix) run only the distance head. Returns the bytes kept: 2 D per vertex in fp16
        (precision "fp16", the default on CUDA), 4 D in fp32. Vertex queries do this on their first call
        unless given ``cache=False``."""
        from .device_state import bind

        return bind(self, device, precision)

    def unbind(self, device=None) -> None:
        """Free the vertex embeddings kept on ``device`` (every device when None)."""
        from .device_state import unbind

        unbind(self, device)

    def invalidate(self):
        """Forget all cached per-device state (weights, embeddings), e.g. after changing ``net`` in place."""
        self._warp.clear()

    def __repr__(self):
        m = f"mesh with {self.mesh.n_input} vertices" if self.mesh is not None else "no mesh (normalized frame)"
        return f"Model(D={self.D}, {m}, querier={'yes' if self.querier is not None else 'no'})"
