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
from neurogf_warp.training.stages import STAGE_TABLE

__all__ = ["calibrate", "ThreadChooser", "fit_budget", "Budget", "short_budget_said", "short_budget_done"]

SLACK = 0.95  # share of the time left that the initial plan fills (the loop itself: logging, validation)


def calibrate(trainer, n: int = 6, stages=STAGES, give_up_s: float | None = None,
              warm_s: dict | None = None) -> dict | None:
    """Seconds per step of each of ``stages``, timed on the trainer itself; its state is restored afterwards.
    With ``give_up_s``, None once the timing (warm-up included) has taken longer than that. ``warm_s``, if
    given, receives each stage's untimed warm-up seconds (first steps, CUDA graph capture).

    (In place rather than on a copy: compiled loss functions are then compiled once, for the real run.)
    """
    saved = (copy.deepcopy(trainer.net.state_dict()), copy.deepcopy(trainer.querier.state_dict()),
             trainer.gen.get_state(), trainer._gen_at_batch, trainer._hard, trainer._hard_at)
    # one untimed step makes the optimizer and touches every buffer; with CUDA graphs, also compile and capture
    warm = 2 + GRAPH_WARMUP + 1 if trainer.graphs else 1
    out = {}
    start = time.perf_counter()
    try:
        for stage in stages:
            trainer.set_modes(stage)
            t_warm = time.perf_counter()
            for i in range(n + warm):
                if i == warm:
                    sync(trainer.device)
                    t0 = time.perf_counter()
                    if warm_s is not None:
                        warm_s[stage] = t0 - t_warm
                trainer.step(stage, 0)
                if give_up_s is not None and time.perf_counter() - start > give_up_s:
                    return None
            sync(trainer.device)
            out[stage] = (time.perf_counter() - t0) / n
    finally:
        trainer.net.load_state_dict(saved[0])
        trainer.querier.load_state_dict(saved[1])
        trainer.gen.set_state(saved[2])
        trainer._gen_at_batch, trainer._hard, trainer._hard_at = saved[3:]
        trainer.reset_stage()
    return out


class ThreadChooser:
    """Chooses the torch thread count of a CPU run on the run's own steps (``threads=0``), at no extra cost.

    At the start of each stage in ``STAGES_TIMED`` every candidate count (1, min(4, n) and torch's own n) runs
    ``warm`` + ``timed`` real training steps, and the count whose timed steps have the lowest median is kept; every
    ``retry_s`` seconds of the stage the trial runs again, since other jobs come and go. On a busy machine several
    threads can be 3-10x slower than one (OpenMP threads wait on each other); on an idle one two threads were 1.6x
    faster. Timing the candidates on extra steps before the run took 14-40 s of a 20 s budget on a 2-core
    machine; here a step is never wasted.
    """

    STAGES_TIMED = tuple(n for n, s in STAGE_TABLE.items() if s.thread_trial)  # the stages that fill a CPU run
    MIN_STEPS = 100  # shorter stages stay at the count in use (one thread at first)

    def __init__(self, warm: int = 1, timed: int = 5, retry_s: float = 30.0):
        import torch

        n = torch.get_num_threads()
        self.candidates = sorted({1, min(4, n), n})
        self.warm, self.timed, self.retry_s = warm, timed, retry_s
        self.chosen = {}  # stage -> count (the latest choice)
        self._stage, self._timed_stage, self._i, self._times, self._since = None, None, 0, {}, 0.0

    def begin(self, stage: str, planned: int | None = None) -> None:
        """A stage starts (``planned`` steps): time the candidates on its first steps if it is one of
        ``STAGES_TIMED`` and long enough (``MIN_STEPS``; in a short stage the trial would be most of it)."""
        long_enough = planned is None or planned >= self.MIN_STEPS
        self._timed_stage = stage if stage in self.STAGES_TIMED and len(self.candidates) > 1 and long_enough else None
        if stage in self.STAGES_TIMED and len(self.candidates) == 1:
            self.chosen[stage] = self.candidates[0]
        if self._timed_stage is not None:
            self._trial()
        else:  # other stages: the count chosen last, else one thread (never a count left over from a cut trial)
            self._stage = None
            self._set(list(self.chosen.values())[-1] if self.chosen else self.candidates[0])

    def _trial(self) -> None:
        self._stage, self._i, self._since = self._timed_stage, 0, 0.0
        self._times = {c: [] for c in self.candidates}
        self._set(self.candidates[0])

    def step_done(self, seconds: float) -> None:
        """After a step of the current stage that took ``seconds``."""
        if self._stage is None:
            if self._timed_stage is not None:
                self._since += seconds
                if self._since >= self.retry_s:
                    self._trial()
            return
        per = self.warm + self.timed
        c = self.candidates[self._i // per]
        if self._i % per >= self.warm:
            self._times[c].append(seconds)
        self._i += 1
        if self._i == per * len(self.candidates):
            best = min(self.candidates, key=lambda k: sorted(self._times[k])[len(self._times[k]) // 2])
            self.chosen[self._stage] = best
            self._set(best)
            self._stage = None
        elif self._i % per == 0:
            self._set(self.candidates[self._i // per])

    @staticmethod
    def _set(count: int) -> None:
        import torch

        torch.set_num_threads(count)


# Short budgets: the default batches (65K distance pairs, 4K paths) gave the bunny 2,165 joint steps in 60 s and
# 0.82% MRE; half the batches 3,530 steps and 0.69%, a quarter 5,360 and 0.59% (igea: 0.47% -> 0.46% at half; H100,
# 2026-11-24; docs/performance.md). At 300 s a quarter also won: bunny 0.41% -> 0.37% (19,664 -> 61,126 joint
# steps), igea 0.31% -> 0.27%; an eighth at 60 s (bunny 0.52%) did not clearly beat a quarter on the GPU, whose
# small steps are bound by kernel count, not size. On a 2-core CPU, where a step's time follows its size, the cpu
# preset makes ~170 joint steps in 60 s: a quarter of its batches gave fandisk 1.11% -> 0.80% (60 s), a sixteenth
# 0.68%; over the seven small meshes at 60 s the mean MRE went 0.84% -> 0.78% from a quarter to a sixteenth (spot
# and cow 5% worse, the others better) and 180 s gave spot 0.61%, fandisk 0.59% (full batches: 0.74%, 0.75%). The
# SDF error rose 24% on average (alligator 2.3x) although the SDF batches stop at a quarter (MIN_SDF_SCALE), until
# the cpu preset's refine_sdf ratio went 0.1 -> 1.0 (then 46% below the quarter's; presets.py). So a
# budget that fits fewer than SHORT_BUDGET_STEPS joint steps at the full batches trains on batches halved until
# that many fit, down to the device's MIN_BATCH_SCALE.
SHORT_BUDGET_STEPS = 60_000
MIN_BATCH_SCALE = {"cuda": 0.25, "cpu": 1 / 16}
MIN_SDF_SCALE = 0.25  # SDF batches (joint stage's SDF points, querier / refine_sdf) shrink at most this far


def short_budget_scale(joint_steps: int, device_type: str = "cuda") -> float:
    """The batch factor (1, 1/2, ... down to ``MIN_BATCH_SCALE[device_type]``) for a budget that fits
    ``joint_steps`` joint steps at the full batches."""
    floor = MIN_BATCH_SCALE.get(device_type, MIN_BATCH_SCALE["cuda"])
    scale = 1.0
    while scale > floor and joint_steps < SHORT_BUDGET_STEPS * scale:
        scale /= 2
    return scale


def short_budget_said(scale: float) -> str:
    """What a short-budget run says before its steps: the batch factor, and no step count (the calibration's few
    steps leave out the loop's own costs, which dominate small batches on a CPU: a run planned at 2,000 joint steps
    made 58)."""
    return (f"short budget: batches x{scale:g} for more steps; the step count follows the measured speed (the last "
            "lines say how many ran)")


def short_budget_done(plan: dict, made: int) -> str:
    """What a short-budget run says after its steps: the joint steps made, and the calibration's plan beside it."""
    planned = int(plan["planned_joint_steps"])
    line = f"short budget: {made:,} joint steps ran at batches x{plan['scale']:g}"
    if made and planned > 1.25 * made:
        line += (f" ({planned:,} planned from the first steps' time: the training loop took "
                 f"{planned / made:.1f}x that time a step)")
    elif not made:
        line += f" ({planned:,} planned from the first steps' time: the budget ended first)"
    return line


def fit_budget(cfg: TrainConfig, per_step: dict, seconds: float) -> TrainConfig:
    """A copy of ``cfg`` whose joint steps (other stages by their ratios) fill ``SLACK`` x ``seconds``, given
    the seconds per step of each stage."""
    fixed = sum(per_step[s] * cfg.explicit_steps(s) for s in STAGES if cfg.explicit_steps(s) is not None)
    free = [s for s in STAGES if cfg.explicit_steps(s) is None]
    capped = [s for s in free if STAGE_TABLE[s].max_steps is not None]  # ratio x joint steps up to a cap
    per_joint = sum(per_step[s] * cfg.ratio(s) for s in free if s not in capped)
    avail = SLACK * seconds - fixed
    at_cap = []  # capped stages whose ratio x joint steps pass their cap: they cost their cap's time instead
    while True:
        joint = (avail - sum(per_step[s] * STAGE_TABLE[s].max_steps for s in at_cap)) / (
            per_joint + sum(cfg.ratio(s) * per_step[s] for s in capped if s not in at_cap))
        over = [s for s in capped if s not in at_cap and cfg.ratio(s) * joint > STAGE_TABLE[s].max_steps]
        if not over:
            break
        at_cap += over
    joint = max(1, int(joint))  # a budget too small for even this is said so (training.quality)
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
    cap : the most joint steps any plan may hold (``fill_budget=False``: the preset's own), or None
    """

    MIN_MEASURED = 5  # steps of a stage before its own measured time is trusted

    def __init__(self, cfg: TrainConfig, deadline: float, estimate: dict, cap: int | None = None):
        self.cfg, self.deadline, self.cap = cfg, deadline, cap
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
        (the later stages follow by their ratios); after it, the remaining stages are scaled together. When not
        even that fits, the floor plan (``floor``): the current stage stops now, later refinements get none."""
        if stage_i >= len(STAGES):
            return dict(steps)
        left = self.deadline - (time.perf_counter() if now is None else now)
        t = self.per_step()
        cur = STAGES[stage_i]

        def cost(plan):
            return sum(t[s] * max(0, plan[s] - (step if i == stage_i else 0))
                       for i, s in enumerate(STAGES) if i >= stage_i)

        def plan_for(x):
            if stage_i <= STAGES.index("joint"):
                x = x if self.cap is None else min(x, self.cap)
                plan = dict(steps, **{s: n for s, n in self.cfg.stage_steps(joint=int(x)).items()
                                      if STAGES.index(s) >= stage_i})
            else:
                x = x if self.cap is None else min(x, 1.0)  # capped: never more than planned
                plan = dict(steps)
                for s in STAGES[stage_i:]:
                    plan[s] = max(1 if steps[s] > 0 else 0, int(round(x * steps[s])))
            plan[cur] = max(plan[cur], step)
            return plan

        if stage_i <= STAGES.index("joint"):
            lo = max(step, 1) if cur == "joint" else 1
            hi = max(lo, 1)
            while cost(plan_for(hi)) <= left and hi < (10**9 if self.cap is None else self.cap):
                hi *= 2
        else:
            lo, hi = 0.0, 1.0
            while cost(plan_for(hi)) <= left and hi < (1e6 if self.cap is None else 1.0):
                hi *= 2
        if cost(plan_for(lo)) > left:  # the floor, and of the later stages' planned steps as many as still fit
            plan = self.floor(steps, stage_i, step)
            want = plan_for(lo)
            for s in STAGES[stage_i + 1:]:
                spare = left - cost(plan)
                if spare <= 0:
                    break
                plan[s] = max(plan[s], min(want[s], int(spare / max(t[s], 1e-9))))
            return self._until_measured(plan, cur, step, t[cur], left)
        for _ in range(60):  # bisection: the largest plan that fits
            mid = (lo + hi) // 2 if isinstance(lo, int) else (lo + hi) / 2
            if mid == lo:
                break
            if cost(plan_for(mid)) <= left:
                lo = mid
            else:
                hi = mid
        return self._until_measured(plan_for(lo), cur, step, t[cur], left)

    def _until_measured(self, plan: dict, stage: str, step: int, per_step: float, left: float) -> dict:
        """A stage whose own time is not measured yet runs at least until it is (``MIN_MEASURED`` steps, when they
        fit by the estimate): a calibration slowed by a passing load spike otherwise plans a stage too short to
        reach its first re-plan (a 50x spike left the joint stage 4 steps of a 20 s budget)."""
        need = self.MIN_MEASURED - self.done[stage]
        if self.cap is None and need > 0 and plan[stage] > 0 and need * per_step <= left:
            plan = dict(plan, **{stage: max(plan[stage], step + need)})
        return plan

    def just_measured(self, stage: str, unrecorded: int) -> bool:
        """True at the step where ``stage``'s own time becomes measured (``unrecorded`` steps not yet recorded):
        the loop re-plans then, from the stage's own time."""
        return self.done[stage] < self.MIN_MEASURED <= self.done[stage] + unrecorded

    @staticmethod
    def floor(steps: dict, stage_i: int, step: int) -> dict:
        """The least a run out of time still does: the current stage stops after ``step`` steps (the querier and
        joint stages after at least one, without which there is no model), a joint stage not yet begun gets one
        step, and the refinements after it none."""
        plan = dict(steps)
        joint = STAGES.index("joint")
        for i, s in enumerate(STAGES[stage_i:], stage_i):
            least = 1 if i <= joint else 0
            plan[s] = max(step, least) if i == stage_i else least
        return plan

    def near_deadline(self, stage: str, now: float) -> bool:
        """True when two more steps of ``stage`` would reach the deadline: the loop then re-plans every step."""
        return now + 2 * self.per_step()[stage] >= self.deadline
