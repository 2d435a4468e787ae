"""Never a silently bad model: the held-out validation error against the heat method's on the same pairs, and
the warnings a run gives when its model is, or is predicted to be, worse than that baseline.

A run's dataset holds ``test_src``, sources never trained on, with their full solver distance rows
``test_dist`` (normalized units). The validation MRE is the network's mean relative error over those pairs
(mean over sources of the mean over that source's vertices at a finite distance > 0); the heat method
(potpourri3d, optional) is scored on exactly the same pairs. A model whose validation MRE is above the heat
method's, or a budget that leaves too little training, gives a ``ModelQualityWarning``, a line on stderr, an
entry in the run's log and fields in the model file's metadata (``validation_mre``, ``heat_mre``,
``worse_than_heat``, ``quality_warning``).
"""
from __future__ import annotations

import warnings

import numpy as np

from neurogf_warp.common.checks import say

__all__ = ["ModelQualityWarning", "heat_validation_mre", "validation_mre", "final_verdict", "budget_verdict",
           "MIN_JOINT_STEPS", "MIN_TRAIN_SHARE"]

# A plan below either figure is predicted too small, before the run starts. Both are floors, not a promise:
# the end-of-run comparison with the heat method is the check that counts. The CPU runs of benchmarks/RESULTS.md
# that beat the heat method made 150-770 joint steps with 80-95% of their budget left for training after the
# dataset and set-up; the 120 s teapot of issue 24, 16.9% MRE, had 37% left.
MIN_JOINT_STEPS = 100
MIN_TRAIN_SHARE = 0.4


class ModelQualityWarning(UserWarning):
    """The trained model is worse than the heat method on held-out pairs, or its budget is predicted too small."""


def validation_mre(pred: np.ndarray, gt: np.ndarray) -> float:
    """Mean over sources of the mean relative error over that source's pairs with a finite truth > 0.

    pred, gt : (T, V) distances in the same units (predictions that are not finite count as error 1)."""
    errs = []
    for p, g in zip(np.asarray(pred, np.float64), np.asarray(gt, np.float64)):
        ok = np.isfinite(g) & (g > 0)
        if ok.any():
            e = np.abs(p[ok] - g[ok]) / g[ok]
            errs.append(float(np.where(np.isfinite(e), e, 1.0).mean()))
    return float(np.mean(errs)) if errs else float("nan")


def heat_validation_mre(vertices, faces, test_src, test_dist) -> float | None:
    """The heat method's validation MRE on the dataset's held-out pairs (``validation_mre``); None when
    potpourri3d is not installed or there are no test sources."""
    from neurogf_warp.dataset.heat import heat_available, heat_distances

    if not heat_available() or len(test_src) == 0:
        return None
    return validation_mre(heat_distances(vertices, faces, test_src), test_dist)


def _emit(message: str, progress: bool) -> None:
    # a warning whatever ``progress`` says (a quiet run is no excuse for silence); no second stderr line beside it
    warnings.warn(message, ModelQualityWarning, stacklevel=3)


def budget_verdict(joint_steps: int, train_share: float, sources: int, sources_asked: int,
                   progress: bool = True) -> str | None:
    """Before the steps: a message (also warned) when the planned work is predicted too small, else None.

    joint_steps : the joint steps the budget plan holds; train_share : the part of the budget left for the steps
    after the dataset and set-up; sources / sources_asked : distance sources the dataset has / was asked for.
    """
    why = []
    if joint_steps < MIN_JOINT_STEPS:
        why.append(f"only {joint_steps} joint steps fit (fewer than {MIN_JOINT_STEPS})")
    if train_share < MIN_TRAIN_SHARE:
        why.append(f"only {train_share:.0%} of the budget is left for training after the dataset and set-up")
    if not why:
        return None
    msg = ("the budget is predicted too small for a good model: " + "; ".join(why)
           + f" ({sources} of {sources_asked} ground-truth sources). Raise budget_seconds (--budget-seconds)")
    _emit(msg, progress)
    return msg


def final_verdict(val_mre: float, heat_mre: float | None, progress: bool = True) -> dict:
    """After the steps: the metadata fields, warning when the model is worse than the heat method.

    Returns {"validation_mre", "heat_mre", "worse_than_heat" (None without potpourri3d), "quality_warning"}."""
    val = None if val_mre is None or not np.isfinite(val_mre) else float(val_mre)
    out = {"validation_mre": val, "heat_mre": heat_mre, "worse_than_heat": None, "quality_warning": None}
    if val is None:
        say(progress, "validation: the dataset has no held-out sources, so the model's error is unknown")
        return out
    if heat_mre is None:
        say(progress, f"validation MRE {val:.3%} on held-out sources (heat method not compared: potpourri3d is not "
                      'installed, pip install "neurogf-warp[heat]")')
        return out
    out["worse_than_heat"] = bool(val > heat_mre)
    if out["worse_than_heat"]:
        msg = (f"the model is worse than the heat method on held-out sources: validation MRE {val:.3%}, heat "
               f"method {heat_mre:.3%} on the same pairs. Train longer (budget_seconds / --budget-seconds) or use "
               "the heat method")
        out["quality_warning"] = msg
        _emit(msg, progress)
    else:
        say(progress, f"validation MRE {val:.3%} on held-out sources (heat method {heat_mre:.3%} on the same pairs)")
    return out
