"""Fitting a run's step counts to a wall-clock budget that covers the whole call.

``calibrate`` times a few steps of each stage; ``fit_budget`` scales the joint steps (the other stages follow
by their ratios) so the plan fits the time left; ``Budget`` re-plans the steps of the current and later stages
while the run goes, from the step times it measures, so that a busy machine or a poor first estimate does not
push the run past its deadline.
"""
from __future__ import annotations

import copy
import dataclasses
import time

from neurogf_warp.training.acceleration import GRAPH_WARMUP, sync
from neurogf_warp.training.config import STAGES, TrainConfig

__all__ = ["calibrate", "fastest_threads", "fit_budget", "Budget"]

SLACK = 0.95  # share of the time left that the initial plan fills (the loop itself: logging, validation)


def calibrate(trainer, n: int = 6) -> dict:
    """Seconds per step of each stage, timed on the trainer itself; its state is restored afterwards.

    (In place rather than on a copy: compiled loss functions are then compiled once, for the real run.)
    """
    saved = (copy.deepcopy(trainer.net.state_dict()), copy.deepcopy(trainer.querier.state_dict()),
             trainer.gen.get_state(), trainer._gen_at_batch)
    warm = 2 + (GRAPH_WARMUP + 1 if trainer.graphs else 0)  # and the capture, when graphs are on
    out = {}
    try:
        for stage in STAGES:
            trainer.set_modes(stage)
            for i in range(n + warm):
                if i == warm:
                    sync(trainer.device)
                    t0 = time.perf_counter()
                trainer.step(stage, 0)
            sync(trainer.device)
            out[stage] = (time.perf_counter() - t0) / n
    finally:
        trainer.net.load_state_dict(saved[0])
        trainer.querier.load_state_dict(saved[1])
        trainer.gen.set_state(saved[2])
        trainer._gen_at_batch = saved[3]
        trainer.reset_stage()
    return out


def fastest_threads(trainer) -> tuple:
    """(count, seconds per step of each stage): the torch thread count among 1, min(4, n) and torch's own count n
    with which this run's planned steps (``trainer.steps``, timed by ``calibrate``) take least time; torch is left
    at that count."""
    import torch

    n = torch.get_num_threads()
    best = None
    for c in sorted({1, min(4, n), n}):
        torch.set_num_threads(c)
        per = calibrate(trainer, n=4)
        cost = sum(per[s] * max(trainer.steps[s], 1) for s in STAGES)
        if best is None or cost < best[0]:
            best = (cost, c, per)
    torch.set_num_threads(best[1])
    return best[1], best[2]


def fit_budget(cfg: TrainConfig, per_step: dict, seconds: float) -> TrainConfig:
    """A copy of ``cfg`` whose joint steps (other stages by their ratios) fill ``SLACK`` x ``seconds``, given
    the seconds per step of each stage."""
    fixed = sum(per_step[s] * cfg.explicit_steps(s) for s in STAGES if cfg.explicit_steps(s) is not None)
    scaled = [s for s in STAGES if cfg.explicit_steps(s) is None and s != "querier"]
    per_joint = sum(per_step[s] * cfg.ratio(s) for s in scaled)
    avail = SLACK * seconds - fixed
    joint = avail / per_joint
    if cfg.schedule.querier_steps is None:  # ratio x joint querier steps, capped
        from neurogf_warp.training.config import QUERIER_MAX

        joint = avail / (per_joint + cfg.ratio("querier") * per_step["querier"])
        if cfg.ratio("querier") * joint > QUERIER_MAX:
            joint = (avail - per_step["querier"] * QUERIER_MAX) / per_joint
    joint = max(10, int(joint))
    sched = cfg.schedule
    epochs = max(1, joint // sched.iters_per_epoch)
    if epochs * sched.iters_per_epoch > joint:  # fewer steps than one epoch: shrink the epoch
        sched = dataclasses.replace(sched, epochs=1, iters_per_epoch=joint)
    else:
        sched = dataclasses.replace(sched, epochs=epochs)
    return dataclasses.replace(cfg, schedule=sched)


class Budget:
    """A deadline for the remaining steps, and re-planning of the step counts to meet it.

    deadline : ``time.perf_counter()`` value by which the last step should be done
    estimate : calibrated seconds per step of each stage (measured times replace them as the run goes)
    """

    MIN_MEASURED = 5  # steps of a stage before its own measured time is trusted

    def __init__(self, cfg: TrainConfig, deadline: float, estimate: dict):
        self.cfg, self.deadline = cfg, deadline
        self.estimate = dict(estimate)
        self.spent = {s: 0.0 for s in STAGES}  # loop seconds and steps per stage
        self.done = {s: 0 for s in STAGES}

    def record(self, stage: str, seconds: float, steps: int):
        self.spent[stage] += seconds
        self.done[stage] += steps

    def per_step(self) -> dict:
        """Seconds per step of each stage: measured where enough steps ran, else the estimate scaled by how
        far the measured stages are off their estimates (the machine's load)."""
        measured = {s: self.spent[s] / self.done[s] for s in STAGES if self.done[s] >= self.MIN_MEASURED}
        ratios = sorted(measured[s] / self.estimate[s] for s in measured if self.estimate[s] > 0)
        load = ratios[len(ratios) // 2] if ratios else 1.0
        return {s: measured.get(s, self.estimate[s] * load) for s in STAGES}

    def replan(self, steps: dict, stage_i: int, step: int, now: float | None = None) -> dict:
        """New step counts for the stages from ``stage_i`` on (``step`` steps of it done) that fit the time left;
        counts of finished stages are kept. Before the end of the joint stage the joint steps are re-fitted
        (the later stages follow by their ratios); after it, the remaining stages are scaled together."""
        if stage_i >= len(STAGES):
            return dict(steps)
        left = self.deadline - (time.perf_counter() if now is None else now)
        t = self.per_step()

        def cost(plan):
            return sum(t[s] * max(0, plan[s] - (step if i == stage_i else 0))
                       for i, s in enumerate(STAGES) if i >= stage_i)

        def plan_for(x):
            if stage_i <= STAGES.index("joint"):
                plan = dict(steps, **{s: n for s, n in self.cfg.stage_steps(joint=int(x)).items()
                                      if STAGES.index(s) >= stage_i})
            else:
                plan = dict(steps)
                for i, s in enumerate(STAGES[stage_i:], stage_i):
                    plan[s] = max(1 if steps[s] > 0 else 0, int(round(x * steps[s])))
            cur = STAGES[stage_i]
            plan[cur] = max(plan[cur], step + 1 if step < steps[cur] else step)
            return plan

        if stage_i <= STAGES.index("joint"):
            lo = step + 1 if STAGES[stage_i] == "joint" else 1
            hi = max(lo, 1)
            while cost(plan_for(hi)) <= left and hi < 10**9:
                hi *= 2
        else:
            lo, hi = 0.0, 1.0
            while cost(plan_for(hi)) <= left and hi < 1e6:
                hi *= 2
        if cost(plan_for(lo)) > left:
            return plan_for(lo)
        for _ in range(60):  # bisection: the largest plan that fits
            mid = (lo + hi) // 2 if isinstance(lo, int) else (lo + hi) / 2
            if mid == lo:
                break
            if cost(plan_for(mid)) <= left:
                lo = mid
            else:
                hi = mid
        return plan_for(lo)
