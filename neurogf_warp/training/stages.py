"""The training stages as data: what each one trains, draws, optimizes and reports (``STAGE_TABLE``).

The trainer and the step loop read a stage's behaviour from its entry here, so that a stage (or the stages of
another network design) is one entry. The table's order is the run's order (``config.STAGES``); a checkpoint
stores a stage by its index in it.
"""
from __future__ import annotations

from dataclasses import dataclass

__all__ = ["Stage", "STAGE_TABLE", "DRAWS", "QUERIER_MAX"]

QUERIER_MAX = 4000  # default querier steps: 0.25 x joint steps, at most this (it only guides the surface term)

# the batch parts a step can draw, in the order ``Stage.draws`` lists them (``Trainer.draw``):
#   sdf           SDF points and values from the pool, ``batch_sdf`` of them
#   querier_sdf   the same, ``batch_querier`` of them
#   distances     (p, q, d) rows of the global, local1 and local2 sets (``batch_g``, ``batch_l1``, ``batch_l2``)
#   paths_global  ``batch_paths_g`` (K, M, 3) global paths;  paths_local: ``batch_paths_l`` local ones
DRAWS = ("sdf", "querier_sdf", "distances", "paths_global", "paths_local")


@dataclass(frozen=True)
class Stage:
    """One training stage.

    Attributes
    ----------
    name : the stage's name (``config.STAGES``, ``<name>_steps``, checkpoints, the loss log)
    trains : the modules whose parameters the stage's optimizer updates, as attribute paths of the Trainer
        ("querier", "net", "net.lifting", ...), in parameter-group order; these alone get ``requires_grad``,
        every other part of the network and the querier is frozen and in eval mode (running BatchNorm statistics)
    train_mode : the trained modules in train mode (batch statistics) rather than eval mode
    lr : the ``ScheduleConfig`` field of the stage's starting learning rate (cosine decay to ``lr_min``)
    draws : the batch parts one step draws (``DRAWS``), in draw order (the order of the generator's draws)
    loss : the Trainer method that turns a batch into the stage's loss terms {name: scalar tensor}
    weighted : the step's loss is the terms weighted by ``losses.WEIGHTS`` (with ``loss_weights``), else their sum
    hard_pairs : a share ``hard_share`` of the distance rows comes from the hard-pair pool
    validates : the held-out MRE is measured every ``val_every`` steps and at the stage's end
    ratio : default steps per joint step (``config.RATIOS``; ``ratios`` and ``<name>_steps`` override it)
    max_steps : a cap on the default (ratio) step count, or None
    thread_trial : on a CPU, the thread counts are tried on this stage's first steps (``budget.ThreadChooser``):
        the stages whose steps fill a CPU run
    """

    name: str
    trains: tuple
    train_mode: bool
    lr: str
    draws: tuple
    loss: str
    weighted: bool = False
    hard_pairs: bool = False
    validates: bool = False
    ratio: float = 1.0
    max_steps: int | None = None
    thread_trial: bool = False


# The reference's stages (§3-§5) and refine_dist (trainer.py's docstring says why each is as it is).
# refine_dist trains in eval mode: eval-mode BN is a fixed affine map, exactly what inference computes.
_STAGES = (
    Stage("querier", trains=("querier",), train_mode=True, lr="lr", draws=("querier_sdf",),
          loss="_loss_querier", ratio=0.25, max_steps=QUERIER_MAX),
    Stage("joint", trains=("net",), train_mode=True, lr="lr",
          draws=("sdf", "distances", "paths_global", "paths_local"), loss="_loss_joint",
          weighted=True, hard_pairs=True, validates=True, ratio=1.0, thread_trial=True),
    Stage("refine_dist", trains=("net.lifting", "net.gdf_head"), train_mode=False, lr="refine_dist_lr",
          draws=("distances",), loss="_loss_refine_dist", weighted=True, hard_pairs=True, validates=True, ratio=1.0,
          thread_trial=True),
    Stage("refine_sdf", trains=("net.sdf_head",), train_mode=True, lr="refine_lr", draws=("querier_sdf",),
          loss="_loss_refine_sdf", ratio=0.1),
    Stage("refine_path", trains=("net.cdw_fc", "net.spf_head"), train_mode=True, lr="refine_path_lr",
          draws=("paths_global",), loss="_loss_refine_path", ratio=0.3),
)
STAGE_TABLE = {s.name: s for s in _STAGES}  # in run order
