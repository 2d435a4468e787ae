"""The eval-mode network as plain layers: BatchNorm folded into each layer's weights and bias (float64)."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

__all__ = ["BN_EPS", "fold_batchnorm", "folded_layers", "NetShape", "net_shape"]

BN_EPS = 1e-5


def fold_batchnorm(layer) -> tuple[np.ndarray, np.ndarray | None]:
    """(W', b') in float64 with eval-mode BatchNorm folded in: W' = diag(s) W, b' = beta - mu s.

    layer: a ``network.FC`` or ``network.PointMLP``; W' has shape (out, in), b' (out,) or None (no BatchNorm).
    """
    mod = layer.linear if hasattr(layer, "linear") else layer.conv
    w = mod.weight.detach().double().cpu().reshape(mod.weight.shape[0], -1)
    if layer.bn is None:
        return w.numpy(), None
    bn = layer.bn
    s = bn.weight.detach().double().cpu() / torch.sqrt(bn.running_var.detach().double().cpu() + BN_EPS)
    b = bn.bias.detach().double().cpu() - bn.running_mean.detach().double().cpu() * s
    return (w * s[:, None]).numpy(), b.numpy()


def folded_layers(net) -> dict:
    """{"lifting", "distance", "sdf", "guidance", "path"}: lists of folded (W, b) layers of a NeuroGFNet."""
    return {"lifting": [fold_batchnorm(m) for m in net.lifting],
            "distance": [fold_batchnorm(m) for m in net.gdf_head],
            "sdf": [fold_batchnorm(m) for m in net.sdf_head],
            "guidance": fold_batchnorm(net.cdw_fc),
            "path": [fold_batchnorm(m) for m in net.spf_head]}


@dataclass(frozen=True)
class NetShape:
    """Layer widths of a NeuroGFNet as read from its weights: each tuple runs from the input width to the output
    width of one stack (``lifting`` (F, ..., D), F = 3 + 6 Fourier octaves; heads (D, ..., 1); ``guidance``
    (2D, D); ``path`` (D + 3, ..., 3)). The kernels are checked against this, not against the configured D."""

    lifting: tuple
    distance: tuple
    sdf: tuple
    guidance: tuple
    path: tuple

    @property
    def D(self) -> int:
        return self.lifting[-1]

    def __str__(self) -> str:
        return (f"lifting {self.lifting}, distance head {self.distance}, SDF head {self.sdf}, "
                f"guidance {self.guidance}, path head {self.path}")


def net_shape(layers: dict) -> NetShape:
    """The ``NetShape`` of ``folded_layers(net)``."""
    def widths(stack):
        return (stack[0][0].shape[1],) + tuple(W.shape[0] for W, _ in stack)

    return NetShape(lifting=widths(layers["lifting"]), distance=widths(layers["distance"]), sdf=widths(layers["sdf"]),
                    guidance=widths([layers["guidance"]]), path=widths(layers["path"]))
