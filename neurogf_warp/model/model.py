"""A trained NeuroGF: the torch network plus the frame it answers in."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from neurogf_warp.mesh.mesh import Mesh
from neurogf_warp.model.network import NeuroGFNet, SdfQuerier

__all__ = ["Model", "DeviceState"]


class DeviceState(Protocol):
    """What a model keeps on one device for its queries, as the model sees it (the inference stage's
    ``QueryState``; the model stage does not import it)."""

    def unbind(self) -> None:
        """Free the kept vertex embeddings and everything made from them."""

    def close(self) -> None:
        """Free everything kept on the device."""


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
    landmarks : (V, K) float32 or None
        For a network with ``landmarks=K`` (``net.landmarks``): the exact geodesic distances from every mesh vertex
        (the mesh file's numbering) to its K landmark vertices, normalized units (multiply by ``1 / scale`` for
        mesh units); an entry across components is ``network.LANDMARK_UNREACHED``, the rows of vertices no face
        uses are NaN. None for other networks, and for one loaded without its mesh (which cannot answer).

    Per-device state (folded weights, packed tensor-core weights, mesh tables, kept vertex embeddings) is made
    by the inference stage (``neurogf_warp.bind``, the queries) and kept in ``_states`` (device name -> a
    ``DeviceState``); ``invalidate()`` frees all of it (call it after changing the network in place),
    ``unbind()`` frees the kept embeddings.
    """

    net: NeuroGFNet
    querier: SdfQuerier | None = None
    mesh: Mesh | None = None
    center: np.ndarray = field(default_factory=lambda: np.zeros(3))
    scale: float = 1.0
    config: dict = field(default_factory=dict)
    mesh_frame: bool = False
    landmarks: np.ndarray | None = None
    _states: dict = field(default_factory=dict, repr=False)  # device name -> DeviceState

    def __post_init__(self):
        self.net.eval()
        if self.querier is not None:
            self.querier.eval()
        self.center = np.asarray(self.center, dtype=np.float64).reshape(3)
        self.scale = float(self.scale)
        if self.landmarks is not None:
            self.landmarks = np.ascontiguousarray(self.landmarks, dtype=np.float32)
            k = self.net.landmarks
            n = None if self.mesh is None else self.mesh.n_input
            if not k or self.landmarks.ndim != 2 or self.landmarks.shape[1] != k or n is None or \
                    len(self.landmarks) != n:
                raise ValueError(f"landmarks must be (mesh vertices, K) = ({n}, {k}) for this network and its mesh, "
                                 f"got {self.landmarks.shape}")
            # the torch network looks its landmark rows up by the vertices' float32 coordinates
            import torch

            self.net.landmark_table.set_table(torch.from_numpy(self.normalized_vertices()),
                                              torch.from_numpy(self.landmarks))

    @property
    def D(self) -> int:
        return self.net.D

    @property
    def in_mesh_frame(self) -> bool:
        """True when inputs/outputs are in the mesh's coordinates (a mesh is attached, or its frame was kept)."""
        return self.mesh is not None or self.mesh_frame

    def normalized_vertices(self) -> np.ndarray:
        """(V, 3) float32: the mesh's vertices (file numbering) in the network's frame, ``(x - center) * scale``
        rounded once to float32, as training and the landmark lookup see them."""
        return ((np.asarray(self.mesh.vertices, np.float64) - self.center) * self.scale).astype(np.float32)

    def internal_landmarks(self) -> np.ndarray:
        """(V, K) float32: ``landmarks`` in the mesh's internal vertex order (input vertices merged into one internal
        vertex share their distances); needs the mesh and the table."""
        m = self.mesh
        used = m.input_to_internal >= 0
        rows = np.empty((len(m.internal_vertices), self.net.landmarks), np.float32)
        rows[m.input_to_internal[used]] = self.landmarks[used]
        return rows

    def unbind(self, device=None) -> None:
        """Free the vertex embeddings kept on ``device`` (a Warp device or its name, "cpu" or "cuda:N"; every
        device when None) and everything made from them; see ``neurogf_warp.bind``."""
        for name, state in self._states.items():
            if device is None or name == str(device):
                state.unbind()

    def invalidate(self):
        """Free all per-device state (weights, tables, embeddings), e.g. after changing ``net`` in place."""
        for state in self._states.values():
            state.close()
        self._states.clear()

    def __repr__(self):
        m = f"mesh with {self.mesh.n_input} vertices" if self.mesh is not None else "no mesh (normalized frame)"
        return f"Model(D={self.D}, {m}, querier={'yes' if self.querier is not None else 'no'})"
