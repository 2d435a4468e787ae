"""Work a call does after its deadline, counted on the calling thread's CPU clock.

A budget's promise is about the work a call chooses to do: it stops starting steps in time and keeps what it does
after the deadline short. The wall clock past a deadline also counts the time other jobs held the cores (on a busy
2-core machine several times the work itself). The calling thread's CPU clock counts only its own work, and that
thread runs every step, the validation and the saving (torch's extra threads only share its parallel loops), so on
an idle machine its CPU time past the deadline is at most the wall time past it: a bound on it holds under any load
and still fails when the call overruns by doing more work.
"""
from __future__ import annotations

import threading
import time


class LateWork:
    """``with LateWork(seconds) as late: call()``: afterwards ``late.cpu_s`` is the calling thread's CPU time spent
    after ``seconds`` of wall time had passed (0 if the call ended first), ``late.wall_s`` the call's wall time and
    ``late.cpu_total_s`` the calling thread's CPU time over the whole call."""

    def __init__(self, seconds: float):
        self.seconds = float(seconds)
        self.cpu_s = self.wall_s = self.cpu_total_s = None
        self._at = None

    def __enter__(self):
        clock = time.pthread_getcpuclockid(threading.get_ident())

        def mark():  # runs on the timer's thread, reads the calling thread's clock
            self._at = time.clock_gettime(clock)

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
        self.cpu_s = 0.0 if self._at is None else max(0.0, cpu - self._at)
        return False
