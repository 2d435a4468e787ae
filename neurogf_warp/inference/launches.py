"""Recorded Warp launches, replayed with a call's parameters: a query's host time becomes a few parameter updates.

``wp.launch`` validates and packs every argument on every call (~20-40 us of host time on CUDA); a small query (a
single path, a single source) is host-bound, so each launch it makes shows in the user's time. A ``Recorded``
keeps one ``wp.Launch`` per key, made on first use, and repacks only the parameters (by name) whose values
changed since its previous call. A recorded launch holds the arrays it was last given: ``clear`` releases them.
"""
from __future__ import annotations

import contextlib

import warp as wp

from neurogf_warp.kernels.inference.tensorcore import param_index

__all__ = ["Recorded"]

_UNSET = object()


class Recorded:
    """Recorded launches of one device, by key; at most ``keep`` per ``group`` (the oldest dropped first), for
    keys that carry a size (one per query size seen).

    cpu_context: a context manager factory entered around CPU replays of kernels recorded with ``cpu_blocks``
    (the tensor-core kernels' cooperative CPU blocks).
    """

    def __init__(self, device, cpu_context=None, keep: int = 16):
        self.device, self.keep = device, keep
        self._cpu_context = cpu_context or contextlib.nullcontext
        self._entries: dict = {}  # key -> [launch, {name: position}, {name: last value}, cpu_blocks, group, held]

    def __contains__(self, key) -> bool:
        return key in self._entries

    def held(self, key):
        """What was stored with the launch (scratch arrays it was recorded with, the rows it is valid for)."""
        return self._entries[key][5]

    def record(self, key, launch: wp.Launch, kernel, *, held=None, group=None, cpu_blocks: bool = False):
        """Keep ``launch`` (a ``wp.launch(..., record_cmd=True)`` of ``kernel``) under ``key``."""
        if group is not None:
            same = [k for k, e in self._entries.items() if e[4] == group]
            for k in same[: max(0, len(same) - self.keep + 1)]:
                del self._entries[k]
        self._entries.pop(key, None)  # re-recorded keys go to the end (dicts keep insertion order)
        self._entries[key] = [launch, param_index(kernel), {}, cpu_blocks, group, held]

    def replay(self, key, params: dict):
        """Launch ``key`` with ``params`` ({name: value}); only values that changed since its last call are packed."""
        launch, index, last, cpu_blocks, _, _ = self._entries[key]
        for name, v in params.items():
            old = last.get(name, _UNSET)
            if old is not v and not (isinstance(v, int) and old == v):
                launch.set_param_at_index(index[name], v)
                last[name] = v
        if self.device.is_cpu and cpu_blocks:
            with self._cpu_context():
                launch.launch()
        else:
            launch.launch()

    def run(self, kernel, dim, params: dict, *, key=None, group=None):
        """Launch a plain ``@wp.kernel`` over ``dim`` with ``params`` naming every argument: recorded the first time
        for ``key`` (default: the kernel and dim), replayed afterwards."""
        key = (kernel.key, dim) if key is None else key
        if key not in self._entries:
            args = [params[a.label] for a in kernel.adj.args]
            cmd = wp.launch(kernel, dim, inputs=args, device=self.device, record_cmd=True)
            self.record(key, cmd, kernel, group=group)
            self._entries[key][2].update(params)
        self.replay(key, params)

    def forget(self, keep=None):
        """Drop recorded launches (all, or those whose key ``keep(key)`` rejects)."""
        if keep is None:
            self._entries.clear()
        else:
            for k in [k for k in self._entries if not keep(k)]:
                del self._entries[k]

    def clear(self):
        self.forget()
