"""Work a training call does after its deadline, counted on the calling thread's CPU clock.

A budget's promise is about the work a call chooses to do: it stops starting steps in time and keeps what it does
after the deadline short. The wall clock past a deadline also counts the time other jobs held the cores (on a busy
2-core machine several times the work itself). The calling thread's CPU clock counts only its own work, and that
thread runs every step, the validation and the saving (torch's extra threads only share its parallel loops), so on
an idle machine its CPU time past the deadline is at most the wall time past it: a bound on it holds under any load
and still fails when the call overruns by doing more work.

On a loaded machine the deadline can also pass before the steps begin, while the set-up that every run needs
(kernels, SDF pool, model) is still under way; the call then takes no step (tested on its own with slowed set-ups).
That set-up is not the budget's to cut, so ``LateWork.late_cpu_s`` leaves out its part after the deadline: what is
left is the steps and the finishing (validation, saving), which the budget decides.
"""
from __future__ import annotations

import threading
import time


class LateWork:
    """``with LateWork(seconds) as late: call()``: afterwards ``late.cpu_s`` is the calling thread's CPU time spent
    after ``seconds`` of wall time had passed (0 if the call ended first), ``late.wall_s`` the call's wall time,
    ``late.cpu_total_s`` the calling thread's CPU time over the whole call and ``late.at_cpu`` its CPU clock at the
    deadline (None if the call ended first)."""

    def __init__(self, seconds: float):
        self.seconds = float(seconds)
        self.cpu_s = self.wall_s = self.cpu_total_s = self.at_cpu = None
        self.loop_cpu = None  # the calling thread's CPU clock when the step loop began (watch_steps)

    def __enter__(self):
        clock = time.pthread_getcpuclockid(threading.get_ident())

        def mark():  # runs on the timer's thread, reads the calling thread's clock
            self.at_cpu = time.clock_gettime(clock)

        self._timer = threading.Timer(self.seconds, mark)
        self._timer.daemon = True
        self._cpu0 = time.thread_time()
        self._t0 = time.perf_counter()
        self._timer.start()
        return self

    def __exit__(self, *exc):
        cpu, self.wall_s = time.thread_time(), time.perf_counter() - self._t0
        self._timer.cancel()
        self._timer.join()
        self.cpu_total_s = cpu - self._cpu0
        self.cpu_s = 0.0 if self.at_cpu is None else max(0.0, cpu - self.at_cpu)
        return False

    def watch_steps(self, runner_class):
        """Record when ``runner_class`` (``neurogf_warp.training.loop.Runner``) starts its step loop; returns the
        original ``__call__`` so that the caller can put it back (or use pytest's monkeypatch on the result)."""
        original = runner_class.__call__
        late = self

        def call(self, *a, **k):
            if late.loop_cpu is None:
                late.loop_cpu = time.thread_time()
            return original(self, *a, **k)

        return call

    @property
    def late_cpu_s(self) -> float:
        """``cpu_s`` without the set-up's part after the deadline (from the deadline to the step loop's start)."""
        setup = 0.0
        if self.at_cpu is not None and self.loop_cpu is not None:
            setup = max(0.0, self.loop_cpu - self.at_cpu)
        return max(0.0, self.cpu_s - setup)
