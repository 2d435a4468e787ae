"""The heat method (potpourri3d, the optional ``heat`` extra): the baseline a trained model must beat.

Training compares its held-out validation error with the heat method's on the same pairs, and evaluation reports
both; both stages import it from here.
"""
from __future__ import annotations

import importlib.util

import numpy as np

__all__ = ["HEAT_HINT", "heat_available", "require_heat", "heat_distances", "HeatJob"]

HEAT_HINT = 'the heat-method comparison needs potpourri3d: pip install "neurogf-warp[heat]"'


def heat_available() -> bool:
    """True when potpourri3d can be imported."""
    return importlib.util.find_spec("potpourri3d") is not None


def require_heat() -> None:
    """Raise ImportError (naming the ``heat`` extra) when potpourri3d is not installed."""
    if not heat_available():
        raise ImportError(HEAT_HINT)


def heat_distances(vertices, faces, sources, on_row=None) -> np.ndarray:
    """Heat-method geodesic distances (potpourri3d's defaults) from each source vertex to every vertex.

    vertices : (V, 3) float, faces : (F, 3) int, sources : (S,) vertex ids; on_row() is called after each row.
    Returns (S, V) float64 in the units of ``vertices``.
    """
    require_heat()
    import potpourri3d as pp3d

    solver = pp3d.MeshHeatMethodDistanceSolver(np.asarray(vertices, np.float64), np.asarray(faces, np.int64))
    out = np.empty((len(sources), len(vertices)), np.float64)
    for i, s in enumerate(np.asarray(sources).reshape(-1)):
        out[i] = solver.compute_distance(int(s))
        if on_row is not None:
            on_row()
    return out


class HeatJob:
    """Heat-method distances from ``sources`` made in a separate process while the caller goes on.

    Why a process: potpourri3d holds the GIL through its set-up, which grows fast with the mesh (0.05 s at 2.9K
    vertices, 6.4 s at 134K, over 9 minutes at 2.2M on the GPU machine's CPU): in the training's own thread it
    stopped the steps for that long and overran a budget. ``rows(timeout)`` waits at most ``timeout`` seconds
    (None: as long as it takes), then stops the process. A plain subprocess of this package
    (``workers.start_package_process``): a user's script needs no ``__main__`` guard.
    """

    def __init__(self, vertices, faces, sources):
        import tempfile
        import threading
        import time

        from neurogf_warp.ground_truth.workers import start_package_process

        require_heat()
        self.t_start = time.perf_counter()
        self.seconds = None  # the job's wall time once its rows are back
        self._log = tempfile.TemporaryFile()
        self._proc = start_package_process("neurogf_warp.dataset.heat", "_serve", self._log)
        self._result, self._error = None, None
        msg = (np.asarray(vertices, np.float64), np.asarray(faces, np.int64), np.asarray(sources).reshape(-1))
        self._thread = threading.Thread(target=self._talk, args=(msg,), daemon=True)
        self._thread.start()

    def _talk(self, msg):
        import pickle
        import time

        try:
            pickle.dump(msg, self._proc.stdin, protocol=pickle.HIGHEST_PROTOCOL)
            self._proc.stdin.close()
            kind, value = pickle.load(self._proc.stdout)
            if kind == "rows":
                self._result = value
                self.seconds = time.perf_counter() - self.t_start
            else:
                self._error = str(value)
        except Exception as e:  # noqa: BLE001 - a dead or stopped process: said by rows()
            self._error = f"the heat-method process stopped ({type(e).__name__}: {e})"

    def rows(self, timeout: float | None = None):
        """(S, V) float32 distances, or (None, why) when the job failed or did not finish within ``timeout``."""
        self._thread.join(timeout)
        if self._thread.is_alive():
            self.close()
            return None, f"the heat method did not finish within the time left ({timeout:.0f} s)"
        if self._result is None:
            try:
                self._proc.wait(timeout=5)  # let its last words reach the log
            except Exception:  # noqa: BLE001 - still running: stopped by close()
                pass
            self._log.seek(0)
            tail = self._log.read().decode(errors="replace").strip().splitlines()[-1:]
            self.close()
            why = tail[0].strip() if tail else f"exit status {self._proc.returncode}"
            return None, f"{self._error or 'no answer'} ({why})"
        self.close()
        return self._result, None

    def close(self):
        if self._proc.poll() is None:
            self._proc.kill()
        self._proc.wait()
        for f in (self._proc.stdout, self._log):
            try:
                f.close()
            except OSError:
                pass


def _serve():
    """The heat job's process: read (vertices, faces, sources), send back ("rows", (S, V) float32)."""
    import os
    import pickle
    import sys

    out = os.fdopen(os.dup(1), "wb")
    os.dup2(2, 1)  # anything printed goes to stderr, not into the message stream
    try:
        vertices, faces, sources = pickle.load(sys.stdin.buffer)
        value = ("rows", heat_distances(vertices, faces, sources).astype(np.float32))
    except Exception as e:  # noqa: BLE001 - reported to the caller
        value = ("error", f"{type(e).__name__}: {e}")
    pickle.dump(value, out, protocol=pickle.HIGHEST_PROTOCOL)
    out.flush()
