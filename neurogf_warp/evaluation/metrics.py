"""Accuracy metrics of geodesic predictions: relative errors, MRE and path Chamfer-L1 (reference §6).

They take numpy or torch arrays and return floats / float64 numpy arrays.
"""
from __future__ import annotations

import numpy as np

__all__ = ["relative_errors", "mre", "chamfer_l1"]


def _np(x) -> np.ndarray:
    if hasattr(x, "detach"):  # a torch tensor
        return x.detach().cpu().numpy()
    return np.asarray(x)


def relative_errors(pred, gt) -> np.ndarray:
    """|pred - gt| / gt over the pairs with a finite, positive gt (the source itself is dropped).

    pred, gt : arrays of the same shape (numpy or torch), same units -> (n,) float64, n = the kept pairs.
    The paper's MRE has no epsilon; excluding gt == 0 is the same as excluding the source vertex.
    """
    p = _np(pred).astype(np.float64).ravel()
    g = _np(gt).astype(np.float64).ravel()
    ok = np.isfinite(g) & (g > 0)
    return np.abs(p[ok] - g[ok]) / g[ok]


def mre(pred, gt) -> float:
    """Mean relative error (a fraction, not %) of ``relative_errors(pred, gt)``; NaN when no pair is kept."""
    r = relative_errors(pred, gt)
    return float(r.mean()) if r.size else float("nan")


def chamfer_l1(pred, gt, chunk: int = 256) -> np.ndarray:
    """Per-path Chamfer-L1 (reference §6): 0.5 * (mean NN distance pred->gt + mean NN distance gt->pred).

    pred : (K, M, 3), gt : (K, N, 3) points (or one path (M, 3), (N, 3)); Euclidean, not squared.
    Returns (K,) float64 in the points' units; ``chunk`` paths are compared at a time.
    """
    import torch

    p = torch.as_tensor(_np(pred), dtype=torch.float64)
    g = torch.as_tensor(_np(gt), dtype=torch.float64)
    if p.ndim == 2:
        p, g = p[None], g[None]
    out = []
    for i in range(0, len(p), chunk):
        d = torch.cdist(p[i:i + chunk], g[i:i + chunk])  # (k, M, N)
        out.append(0.5 * (d.min(2).values.mean(1) + d.min(1).values.mean(1)))
    return torch.cat(out).numpy() if out else np.zeros(0)
