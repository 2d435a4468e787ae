"""Ground-truth distance rows solved on several CPU cores: the calling process's solver and worker processes.

Warp runs a CPU kernel on one thread, so one ``GeodesicSolver`` keeps one core busy. ``DistanceRows`` hands
batches of sources to the caller's solver and to worker processes (``python -m neurogf_warp.ground_truth.workers``,
each with its own solver on the same mesh and settings) and gives the rows back in batch order: every source is
solved on its own, so the rows, and a dataset built from them, are the same with any number of workers.

Workers run the very package their caller runs, whatever the current directory: the caller's package root is
first on their ``sys.path`` and the current directory is not on it (see ``_BOOT``).

Workers are plain subprocesses that talk over pipes (pickled messages), not ``multiprocessing``: a user's script
then needs no ``if __name__ == "__main__":`` guard. They start only when the work left is worth their start-up
(importing Warp, building the graph: about 2 s), ignore Ctrl-C (the caller stops them), and exit when the caller's
end of the pipe closes, so none outlives it. A worker that fails is reported and its batch solved by the caller.
"""
from __future__ import annotations

import contextlib
import os
import pickle
import queue
import subprocess
import sys
import tempfile
import threading
import time
import warnings

import numpy as np

from neurogf_warp.common.checks import integer

__all__ = ["DistanceRows", "cpu_cores", "start_package_process", "MAX_WORKERS"]

MAX_WORKERS = 8  # processes in all (the caller included); each holds Warp and a solver (~0.3 GB)
START_COST_S = 4.0  # start workers only when the batches left take longer than this on the caller alone


def start_package_process(module: str, function: str, stderr) -> subprocess.Popen:
    """A Python subprocess of this very package that runs ``module.function()``, stdin and stdout pipes for
    pickled messages, stderr to ``stderr``.

    ``-c``, not ``-m``: "-m" puts the current directory first on sys.path, where a checkout's (or any)
    neurogf_warp/ folder would shadow the package this process runs; ``_BOOT`` puts this package's root first."""
    import neurogf_warp

    package = os.path.abspath(neurogf_warp.__file__)
    root = os.path.dirname(os.path.dirname(package))
    return subprocess.Popen([sys.executable, "-c", _BOOT, root, package, module, function], stdin=subprocess.PIPE,
                            stdout=subprocess.PIPE, stderr=stderr)


def cpu_cores() -> int:
    """CPU cores this process may run on (its affinity where the OS says, else ``os.cpu_count()``)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return max(1, os.cpu_count() or 1)


class _Worker:
    """One worker process with a solver for the caller's mesh; ``solve(sources)`` -> (rows, V) float32."""

    def __init__(self, mesh, settings: dict):
        self.log = tempfile.TemporaryFile()  # its stderr, shown only if it fails
        self.proc = start_package_process("neurogf_warp.ground_truth.workers", "_serve", self.log)
        self.closing = False
        self.failed = False  # it stopped answering: no more batches for it
        self._ready = False
        try:
            self._send(("mesh", mesh, settings))
        except OSError:
            # it exited before reading (its import failed, say): its first batch fails and the warning then
            # quotes its own error from its log, not this broken pipe
            pass

    def _send(self, msg):
        pickle.dump(msg, self.proc.stdin, protocol=pickle.HIGHEST_PROTOCOL)
        self.proc.stdin.flush()

    def _receive(self):
        kind, value = pickle.load(self.proc.stdout)
        if kind == "error":
            raise RuntimeError(value)
        return value

    def ready(self) -> None:
        """Wait until the worker has built its solver."""
        if not self._ready:
            self._receive()
            self._ready = True

    def solve(self, sources: np.ndarray) -> np.ndarray:
        self._send(("solve", np.asarray(sources, dtype=np.int64)))
        return self._receive()

    def failure(self) -> str:
        """Why the worker failed: the last line of its stderr (the exception, for a Python error), then its exit
        status and the lines before."""
        try:
            self.proc.wait(timeout=2)  # a worker that failed is exiting: let its last words reach the log
        except subprocess.TimeoutExpired:
            pass
        self.log.seek(0)
        lines = [ln for ln in self.log.read().decode(errors="replace").strip().splitlines() if ln.strip()]
        status = "still running" if self.proc.returncode is None else f"exit status {self.proc.returncode}"
        if not lines:
            return f"no message ({status})"
        before = " | ".join(ln.strip() for ln in lines[-5:-1])
        return f"{lines[-1].strip()} ({status}{'; before: ' + before if before else ''})"

    def kill(self):
        """Stop the worker at once (a solve in progress is abandoned)."""
        self.closing = True
        if self.proc.poll() is None:
            self.proc.terminate()

    def close(self):
        """Close its input (an idle worker exits), wait for it, and free its pipes."""
        self.closing = True
        try:
            self.proc.stdin.close()
        except OSError:
            pass
        try:
            self.proc.wait(timeout=5)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
        self.proc.stdout.close()
        self.log.close()


class DistanceRows:
    """Vertex distance rows of batches of sources, from ``solver`` (a CPU or GPU ``GeodesicSolver``) and, on the
    CPU, up to ``workers - 1`` worker processes. Use as a context manager (the workers stop on exit).

    workers : processes in all, the caller included (None: the cores this process may use, at most
        ``MAX_WORKERS``); always 1 on a GPU, where one solver fills the device
    devices : further devices (GPUs), each solving batches in a thread of this process with its own solver of the
        same mesh and settings (``solver.settings``: the same batches, so the same rows)
    """

    def __init__(self, solver, workers: int | None = None, devices=()):
        if workers is not None:
            workers = integer("workers", workers, minimum=1)
        self.solver = solver
        if not solver.device.is_cpu:
            workers = 1
        self.workers = min(MAX_WORKERS, cpu_cores() if workers is None else int(workers))
        self._pool: list[_Worker] = []
        self.worker_batches = 0  # batches the worker processes solved
        self.devices = list(devices)
        self.device_batches = 0  # batches the other devices solved
        self._holds: dict = {}  # batch -> (device solver, event set when the caller is done with the batch)
        self._prefetch = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def close(self):
        for w in self._pool:
            w.close()
        self._pool = []

    def prefetch(self) -> bool:
        """Start the next batch of the running ``rows`` on the GPU now (asking ``more`` as usual), so that it solves
        while the caller works on the batch just yielded; the caller must be done with the solver's state (paths
        traced) and hold its rows. False where nothing was started: the CPU, no further batch, or the solver's
        programs not captured yet."""
        return bool(self._prefetch and self._prefetch())

    def rows(self, batches: list, more=None, hold=None):
        """Yield ``(i, D)`` for batch ``i`` of ``batches`` (arrays of internal source ids), in order, with ``D``
        the (len(batches[i]), V) float32 normalized distances. ``more(i)``, if given, is asked before batch
        ``i > 0`` is started; once it says False no further batch starts (those started are still yielded). On a
        GPU the caller may start the next batch early (``prefetch``). ``hold(i)``: whether the solver that made
        batch ``i`` keeps its state until the caller asks for the next batch (``solver_of(i)`` is that solver,
        e.g. to trace the batch's paths)."""
        n = len(batches)
        lock = threading.Lock()
        state = {"next": 0, "stop": False, "closed": False}
        held = hold or (lambda i: False)

        def claim():
            with lock:
                i = state["next"]
                if state["stop"] or i >= n or (i > 0 and more is not None and not more(i)):
                    state["stop"] = True
                    return None
                state["next"] = i + 1
                return i

        done: queue.Queue = queue.Queue()
        ready: dict = {}
        want = 0
        feeders: list[threading.Thread] = []
        redo: list = []  # batches a worker or device failed on: solved here
        mine = {"i": None}  # a batch whose state this process's solver must keep until it is yielded
        yielding = {"i": None}  # the batch the caller has now

        def solve_here(i):
            t0 = time.perf_counter()
            self.solver.run(batches[i])
            ready[i] = self.solver.vertex_distances()
            if held(i):
                mine["i"] = i
            return time.perf_counter() - t0

        def solve_again():
            # the batch that holds up the others first; a kept state of this solver is given up (solved again
            # later), as the solve overwrites it
            if mine["i"] is not None:
                ready.pop(mine["i"], None)
                redo.append(mine["i"])
                mine["i"] = None
            redo.sort()
            solve_here(redo.pop(redo.index(want)) if want in redo else redo.pop(0))

        started: dict = {}  # the batch prefetch began on the GPU

        def prefetch():
            # this solver's kept batch may be the one being yielded: the caller, asking, is done with it
            if started or mine["i"] not in (None, yielding["i"]) or self.workers > 1 or not self.solver.can_start:
                return False
            i = claim()
            if i is None:
                return False
            mine["i"] = None
            self.solver.start(batches[i])
            started["i"] = i
            return True

        self._prefetch = prefetch

        def collect(block: bool):
            while True:
                try:
                    item = done.get(timeout=0.2) if block else done.get_nowait()
                except queue.Empty:
                    return
                i, d = item[0], item[1]
                if d is None:  # its worker or device failed: solve it here
                    redo.append(i)
                else:
                    ready[i] = d
                    if len(item) > 2 and item[2] is not None:
                        self._holds[i] = item[2]
                block = False

        def emit(i):
            d = ready.pop(i)
            yielding["i"] = i
            try:
                yield i, d
            finally:  # the caller is done with batch i: its solver may go on
                yielding["i"] = None
                if mine["i"] == i:
                    mine["i"] = None
                h = self._holds.pop(i, None)
                if h is not None:
                    h[1].set()

        try:
            while True:
                collect(block=False)
                while want in ready:
                    yield from emit(want)
                    want += 1
                if started:  # prefetched: wait for it
                    i = started.pop("i")
                    self.solver.wait()
                    ready[i] = self.solver.vertex_distances()
                    if held(i):
                        mine["i"] = i
                    continue
                if redo and (mine["i"] is None or want in redo):
                    solve_again()
                    continue
                if mine["i"] is not None:  # this solver keeps a batch that earlier ones, solved elsewhere, hold up
                    collect(block=True)
                    continue
                i = claim()
                if i is None:
                    break
                if not feeders and self.devices and i + 1 < n:
                    feeders = self._start_devices(batches, claim, done, state, held)
                took = solve_here(i)
                if not feeders and self.workers > 1 and took * (n - i - 1) > START_COST_S:
                    feeders = self._start(batches, claim, done)
            while want < state["next"]:
                if want in ready:
                    yield from emit(want)
                    want += 1
                elif redo and (mine["i"] is None or want in redo):
                    solve_again()
                else:
                    collect(block=True)
        finally:
            self._prefetch = None
            if started:  # left with a batch running (an error, the caller stopped): let it end, result unused
                started.clear()
                with contextlib.suppress(Exception):  # do not hide the error that brought us here
                    self.solver.wait()
            with lock:
                state["stop"] = True
            state["closed"] = True  # devices waiting on a kept batch stop waiting
            for h in self._holds.values():
                h[1].set()
            self._holds.clear()
            early = want < state["next"]  # left early (an error, Ctrl-C, the caller stopped): stop the workers
            if early:
                for w in self._pool:
                    w.kill()
            for t in feeders:
                t.join()
            if early:
                self.close()

    def solver_of(self, i: int):
        """The solver that holds batch ``i``'s state while it is yielded (``rows(..., hold=...)``): this process's
        own, or a further device's."""
        h = self._holds.get(i)
        return self.solver if h is None else h[0]

    def _start_devices(self, batches, claim, done, state, held) -> list:
        """A thread per further device; each builds its solver at once."""
        from neurogf_warp.ground_truth.devices import lock_captures

        lock_captures(self.solver)  # its first captures may come while a device's thread captures
        threads = [threading.Thread(target=self._feed_device, args=(d, batches, claim, done, state, held),
                                    daemon=True) for d in self.devices]
        for t in threads:
            t.start()
        return threads

    def _feed_device(self, device, batches, claim, done, state, held):
        """Solve batches on ``device`` until none are left, keeping a held batch's state until the caller is done
        with it; a failure hands its batch back to the caller."""
        from neurogf_warp.ground_truth.devices import capture_lock, lock_captures
        from neurogf_warp.ground_truth.solver import GeodesicSolver

        i = None
        try:
            with capture_lock():  # its uploads and allocations never during another device's graph capture
                solver = lock_captures(GeodesicSolver(self.solver.mesh, device=device, **self.solver.settings))
            while True:
                i = claim()
                if i is None:
                    return
                solver.run(batches[i])
                d = solver.vertex_distances()
                if not held(i):
                    done.put((i, d, None))
                    self.device_batches += 1
                    i = None
                    continue
                kept = threading.Event()
                done.put((i, d, (solver, kept)))
                self.device_batches += 1
                i = None
                while not kept.wait(0.05):
                    if state["closed"]:
                        return
        except Exception as e:  # noqa: BLE001 - the caller solves the batch; the run goes on with fewer devices
            if i is not None:
                done.put((i, None, None))
            warnings.warn(f"ground truth on {device} failed ({type(e).__name__}: {e}); its batches are solved on "
                          f"{self.solver.device}", RuntimeWarning, stacklevel=2)

    def _start(self, batches, claim, done) -> list:
        """Start the workers (once per DistanceRows) and a feeding thread for each; returns the threads."""
        if not self._pool:
            try:
                for _ in range(self.workers - 1):
                    self._pool.append(_Worker(self.solver.mesh, self.solver.settings))
            except (OSError, ValueError, pickle.PicklingError) as e:  # e.g. no Python executable to start
                warnings.warn(f"could not start ground-truth worker processes ({e}); solving in this process only",
                              RuntimeWarning, stacklevel=2)
                self.close()
                self.workers = 1
                return []
        threads = [threading.Thread(target=self._feed, args=(w, batches, claim, done), daemon=True)
                   for w in self._pool if not w.failed]
        for t in threads:
            t.start()
        return threads

    def _feed(self, w: _Worker, batches, claim, done):
        """Give worker ``w`` batches until none are left; a failure hands its batch back to the caller."""
        i = None
        try:
            w.ready()
            while True:
                i = claim()
                if i is None:
                    return
                done.put((i, w.solve(batches[i])))
                self.worker_batches += 1
                i = None
        except (OSError, EOFError, RuntimeError, pickle.UnpicklingError, ValueError) as e:
            w.failed = True
            if i is not None:
                done.put((i, None))
            if not w.closing:
                # the worker's own error is the cause; ours (a closed pipe, a truncated message) only the symptom
                warnings.warn(f"a ground-truth worker process failed: {w.failure()}; its work is done by this "
                              f"process (seen here as {type(e).__name__}: {e})", RuntimeWarning, stacklevel=2)


# The worker's entry point (python -c _BOOT ROOT PACKAGE_FILE): import the caller's package from the caller's
# package root, whatever the current directory holds, check that it is the same file, then serve.
_BOOT = """
import os, sys
root, want = sys.argv[1], sys.argv[2]
here = os.getcwd()
sys.path[:] = [root] + [p for p in sys.path if p not in ("", ".") and os.path.abspath(p) not in (here, root)]
import neurogf_warp
got = os.path.abspath(neurogf_warp.__file__)
if os.path.realpath(got) != os.path.realpath(want):
    raise ImportError(f"the worker imported neurogf_warp from {got}, not the caller's {want}")
import importlib
getattr(importlib.import_module(sys.argv[3]), sys.argv[4])()
"""


def _serve():
    """Worker side: build a solver for the caller's mesh, then solve batches until the pipe closes."""
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C reaches the whole process group; the caller stops us
    out = os.fdopen(os.dup(1), "wb")
    os.dup2(2, 1)  # anything printed (Warp's messages) goes to stderr, not into the message stream
    inp = sys.stdin.buffer

    def send(kind, value):
        pickle.dump((kind, value), out, protocol=pickle.HIGHEST_PROTOCOL)
        out.flush()

    try:
        _, mesh, settings = pickle.load(inp)
        import warp as wp

        wp.config.log_level = wp.LOG_WARNING
        from neurogf_warp.ground_truth.solver import GeodesicSolver

        solver = GeodesicSolver(mesh, device="cpu", **settings)
        send("ready", None)
        while True:
            try:
                _, sources = pickle.load(inp)
            except EOFError:
                return
            solver.run(sources)
            send("rows", solver.vertex_distances())
    except (BrokenPipeError, KeyboardInterrupt):
        return
    except Exception as e:  # noqa: BLE001 - reported to the caller, which solves the batch itself
        try:
            send("error", f"{type(e).__name__}: {e}")
        except OSError:
            pass
        raise


if __name__ == "__main__":
    _serve()
