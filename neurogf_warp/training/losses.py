"""NeuroGF training losses: torch tensors in, scalar tensors out (they run inside the training graph).

Everything is in the normalized unit-sphere frame. Accuracy metrics for evaluation are in ``neurogf_warp.evaluation.metrics``.
"""
from __future__ import annotations

import torch

__all__ = ["WEIGHTS", "l1", "relative_l1", "polyline_length", "length_loss", "surface_loss", "weighted_sum"]

# Loss weights of the official joint training (reference §4).
WEIGHTS = {
    "sdf": 0.1,
    "dist_g": 1.0, "dist_l1": 1.0, "dist_l2": 1.0,
    "path_g": 0.1, "path_l": 0.1,
    "len": 0.1,
    "surf": 0.1,
}


def l1(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Mean absolute error over every element (nn.L1Loss); path losses use it on all xyz of all points."""
    return (pred - target).abs().mean()


def relative_l1(pred: torch.Tensor, target: torch.Tensor, floor: float = 1e-4) -> torch.Tensor:
    """Mean |pred - target| / target: the MRE itself as a loss (targets below ``floor`` count as ``floor``)."""
    return ((pred - target).abs() / target.clamp_min(floor)).mean()


def polyline_length(paths: torch.Tensor) -> torch.Tensor:
    """(..., M, 3) ordered points -> (...) sum of segment lengths."""
    return (paths[..., 1:, :] - paths[..., :-1, :]).norm(dim=-1).sum(-1)


def length_loss(pred_paths: torch.Tensor, gt_paths: torch.Tensor) -> torch.Tensor:
    """L1 between predicted and ground-truth polyline lengths (global paths only in the paper)."""
    return (polyline_length(pred_paths) - polyline_length(gt_paths)).abs().mean()


def surface_loss(querier, points: torch.Tensor) -> torch.Tensor:
    """Mean |SDF| at predicted path points through the frozen querier: pulls paths onto the surface.

    The querier must be in eval mode with frozen parameters; gradients still flow to ``points``.
    """
    return querier(points.reshape(-1, 3)).abs().mean()


def weighted_sum(terms: dict, weights: dict | None = None) -> torch.Tensor:
    """Total loss: sum of weight * term over the terms present (missing weights count 1)."""
    w = WEIGHTS if weights is None else weights
    total = None
    for k, v in terms.items():
        t = w.get(k, 1.0) * v
        total = t if total is None else total + t
    return total
