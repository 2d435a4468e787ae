"""NeuroGF training losses and evaluation metrics.

Losses take torch tensors (they run inside the training graph); metrics take numpy or torch arrays and
return plain floats / numpy arrays. Everything is in the normalized unit-sphere frame.
"""
from __future__ import annotations

import numpy as np
import torch

__all__ = [
    "WEIGHTS", "l1", "relative_l1", "polyline_length", "length_loss", "surface_loss", "weighted_sum",
    "relative_errors", "mre", "chamfer_l1",
]

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


def _np(x) -> np.ndarray:
    if isinstance(x, torch.Tensor):
        return x.detach().cpu().numpy()
    return np.asarray(x)


def relative_errors(pred, gt) -> np.ndarray:
    """|pred - gt| / gt over the pairs with a finite, positive gt (the source itself is dropped).

    The paper's MRE has no epsilon; excluding gt == 0 is the same as excluding the source vertex.
    """
    p = _np(pred).astype(np.float64).ravel()
    g = _np(gt).astype(np.float64).ravel()
    ok = np.isfinite(g) & (g > 0)
    return np.abs(p[ok] - g[ok]) / g[ok]


def mre(pred, gt) -> float:
    """Mean relative error (a fraction, not %)."""
    r = relative_errors(pred, gt)
    return float(r.mean()) if r.size else float("nan")


def chamfer_l1(pred, gt, chunk: int = 256) -> np.ndarray:
    """Per-path Chamfer-L1 (reference §6): 0.5 * (mean NN distance pred->gt + mean NN distance gt->pred).

    pred (K, M, 3), gt (K, N, 3); Euclidean, not squared. Returns (K,) float64.
    """
    p = torch.as_tensor(_np(pred), dtype=torch.float64)
    g = torch.as_tensor(_np(gt), dtype=torch.float64)
    if p.ndim == 2:
        p, g = p[None], g[None]
    out = []
    for i in range(0, len(p), chunk):
        d = torch.cdist(p[i:i + chunk], g[i:i + chunk])  # (k, M, N)
        out.append(0.5 * (d.min(2).values.mean(1) + d.min(1).values.mean(1)))
    return torch.cat(out).numpy() if out else np.zeros(0)
