"""The step loop of a run: stages in order, progress bar, loss log, validation, checkpoints, clean Ctrl-C.

The first Ctrl-C (SIGINT) finishes the current step, writes a checkpoint and raises ``TrainingInterrupted``;
a second one stops at once. With a ``Budget`` the remaining step counts are re-planned every few seconds.

Data-parallel (``ranks``): every rank runs this loop and enters the same collectives, so the decisions that depend on
a clock (re-plans, stopping on Ctrl-C) are taken at step counts every rank knows: at each ``sync`` rank 0's plan and
the next sync's step reach every rank, and a Ctrl-C seen by any rank stops them all there. Validation and checkpoints
are rank 0's alone (``save`` does nothing on the other ranks).
"""
from __future__ import annotations

import signal
import time

import torch

from neurogf_warp.common.progress import Progress
from neurogf_warp.training import losses as L
from neurogf_warp.training.acceleration import set_tf32
from neurogf_warp.training.config import STAGES
from neurogf_warp.training.stages import STAGE_TABLE

__all__ = ["Runner", "TrainingInterrupted"]

REPLAN_EVERY_S = 2.0  # seconds between re-plans of the step counts under a budget (and at every stage start)


class TrainingInterrupted(KeyboardInterrupt):
    """Raised after Ctrl-C once the checkpoint is written; ``.checkpoint`` says where."""

    def __init__(self, message: str, checkpoint: str):
        super().__init__(message)
        self.checkpoint = checkpoint


class Runner:
    """Runs a Trainer from (stage, step) to the end of the last stage.

    save(stage_i, step, history, elapsed) writes a checkpoint; callback(stage, step, terms) is called after every
    step (raising KeyboardInterrupt there stops the run like Ctrl-C); budget: a ``budget.Budget`` or None.
    """

    def __init__(self, trainer, save, ckpt_file: str, progress: bool, callback=None, budget=None, threads=None,
                 ranks=None):
        self.t, self.save, self.ckpt_file = trainer, save, ckpt_file
        self.progress, self.callback, self.budget = progress, callback, budget
        self.threads = threads  # a budget.ThreadChooser (CPU, threads=0) or None
        self.ranks = ranks  # a trainer.Ranks (data-parallel) or None
        self.stop = False
        self.next_sync = 0  # data-parallel: the step of the current stage at which the ranks next agree

    def _on_sigint(self, signum, frame):
        if self.stop:  # second Ctrl-C: give up at once
            raise KeyboardInterrupt
        self.stop = True

    def __call__(self, stage_i: int, step: int, history: dict, elapsed: float):
        t, rt = self.t, self.t.cfg.runtime
        bar = None
        if self.progress:
            done = sum(t.steps[s] for s in STAGES[:stage_i]) + step
            # the budget re-plans the step counts every few seconds; the shown total follows only changes of
            # more than a tenth, so that it does not jump at every re-plan
            bar = Progress(sum(t.steps.values()), "training", unit="step", initial=done, total_tolerance=0.1)
        old = None
        try:
            old = signal.signal(signal.SIGINT, self._on_sigint)
        except ValueError:  # not the main thread: Ctrl-C arrives as KeyboardInterrupt instead
            pass
        tf32 = set_tf32(rt.tf32) if t.device.type == "cuda" else None
        last_save = time.perf_counter()
        try:
            while stage_i < len(STAGES):
                stage = STAGES[stage_i]
                spec = STAGE_TABLE[stage]
                if self.ranks is None:
                    self._replan(stage_i, step, bar)
                elif self._sync(stage_i, step, bar, 0.0, 0):  # interrupted at the end of the last stage
                    self.save(stage_i, step, history, elapsed)
                    raise TrainingInterrupted(
                        f"interrupted at {stage} step {step}/{t.steps[stage]}; checkpoint saved to "
                        f"{self.ckpt_file}. Run again with --resume to continue.", self.ckpt_file)
                t.set_modes(stage)
                if self.threads is not None:
                    self.threads.begin(stage, t.steps[stage])
                acc, acc_n = None, 0
                t0 = seg0 = time.perf_counter()
                seg_steps = 0
                while step < t.steps[stage]:
                    n = t.steps[stage]
                    interrupted = False
                    try:
                        t_step = time.perf_counter()
                        terms = t.step(stage, step)
                        if self.threads is not None:
                            self.threads.step_done(time.perf_counter() - t_step)
                        step += 1
                        seg_steps += 1
                        vals = torch.stack([v.detach().float() for v in terms.values()])
                        acc = vals if acc is None else acc + vals
                        acc_n += 1
                        if self.callback is not None:
                            self.callback(stage, step, terms)
                    except KeyboardInterrupt:
                        interrupted = True
                        if self.ranks is not None:  # every rank stops at the next sync, rank 0 saving
                            interrupted, self.stop = False, True
                    if bar is not None:
                        bar.update(1)
                    if acc_n and (step % rt.log_every == 0 or step == n):
                        row = dict(zip(terms, (acc / acc_n).tolist()))
                        total_loss = float(L.weighted_sum({k: torch.tensor(v) for k, v in row.items()})) \
                            if spec.weighted else sum(row.values())
                        history["loss"].append({"stage": stage, "step": step, "lr": t.lr_at(stage, step - 1),
                                                "loss": total_loss, **row})
                        acc, acc_n = None, 0
                        if bar is not None:
                            bar.set_postfix(f"{stage} loss {total_loss:.4g} lr {t.lr_at(stage, step - 1):.2e}"
                                                + (f" valMRE {history['val'][-1]['mre']:.3%}" if history["val"] else ""))
                    validate = spec.validates and ((rt.val_every and step % rt.val_every == 0) or step == n)
                    if validate and (self.ranks is None or self.ranks.first):
                        history["val"].append({"stage": stage, "step": step, "mre": t.validate()})
                    stopping = interrupted or self.stop
                    if self.ranks is not None:
                        stopping = False
                        if step >= self.next_sync:
                            now = time.perf_counter()
                            stopping = self._sync(stage_i, step, bar, now - seg0, seg_steps)
                            seg0, seg_steps = now, 0
                    if stopping:
                        elapsed += time.perf_counter() - t0
                        t0 = time.perf_counter()
                        self.save(stage_i, step, history, elapsed)
                        raise TrainingInterrupted(
                            f"interrupted at {stage} step {step}/{n}; checkpoint saved to {self.ckpt_file}. "
                            "Run again with --resume to continue.", self.ckpt_file)
                    now = time.perf_counter()
                    if now - last_save > rt.ckpt_every_s:
                        elapsed += now - t0
                        t0 = now
                        self.save(stage_i, step, history, elapsed)
                        last_save = time.perf_counter()
                    measured = self.budget is not None and self.ranks is None and \
                        self.budget.just_measured(stage, seg_steps)
                    # also at a stage's planned end: a stall in the steps last measured (another job) may have
                    # planned the stage too short, and no timed re-plan comes before it ends
                    end = step >= t.steps[stage] and seg_steps > 0
                    if self.budget is not None and self.ranks is None and \
                            (now - seg0 > REPLAN_EVERY_S or measured or end or self.budget.near_deadline(stage, now)):
                        self.budget.record(stage, now - seg0, seg_steps)
                        seg0, seg_steps = now, 0
                        self._replan(stage_i, step, bar)
                if self.budget is not None:
                    self.budget.record(stage, time.perf_counter() - seg0, seg_steps)
                elapsed += time.perf_counter() - t0
                t.share_buffers()  # data-parallel: rank 0's BatchNorm statistics for the next stages and the model
                stage_i, step = stage_i + 1, 0
                self.save(stage_i, step, history, elapsed)
                last_save = time.perf_counter()
            if bar is not None:  # every stage ran to its end: the steps done are the run's total
                bar.finish()
        finally:
            if tf32 is not None:
                set_tf32(tf32)
            if old is not None:
                signal.signal(signal.SIGINT, old)
            if bar is not None:
                bar.close()
        return stage_i, step, history, elapsed

    def _sync(self, stage_i: int, step: int, bar, seconds: float, steps: int) -> bool:
        """Data-parallel: the ranks agree on the step counts (rank 0's re-plan, from its ``steps`` steps of
        ``seconds`` since the last sync) and on the step of the next sync; True when any rank was interrupted."""
        t, stage = self.t, STAGES[stage_i]
        plan, every = None, 1
        if self.ranks.first:
            if self.budget is not None:
                if steps:
                    self.budget.record(stage, seconds, steps)
                plan = self.budget.replan(t.steps, stage_i, step)
            per = self.budget.per_step()[stage] if self.budget is not None else seconds / max(steps, 1)
            if per > 0 and (steps or self.budget is not None):
                # about every REPLAN_EVERY_S seconds, more often near the deadline and until the stage is measured
                every = max(1, int(REPLAN_EVERY_S / per))
                if self.budget is not None:
                    every = min(every, max(1, int((self.budget.deadline - time.perf_counter()) / per / 4)))
                    if self.budget.done[stage] < self.budget.MIN_MEASURED:
                        every = min(every, self.budget.MIN_MEASURED - self.budget.done[stage])
        said = self.ranks.gather((self.stop, plan, every))
        if plan is None:
            plan = said[0][1]
        if plan is not None:
            t.steps = plan
            if bar is not None:
                bar.set_total(sum(t.steps.values()))
        self.next_sync = step + said[0][2]
        return any(s[0] for s in said)

    def _replan(self, stage_i: int, step: int, bar):
        if self.budget is None:
            return
        t = self.t
        t.steps = self.budget.replan(t.steps, stage_i, step)
        if bar is not None:
            bar.set_total(sum(t.steps.values()))
