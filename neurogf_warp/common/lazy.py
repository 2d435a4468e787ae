"""Names a package exports and imports on first use, so that importing the package (and ``--help``) stays light."""
from __future__ import annotations

import importlib
import time

__all__ = ["lazy_exports", "call_started"]

# name -> (start, end) perf_counter seconds of its first-use import: ``ngf.train(...)`` imports torch and the
# training stages (1.5 s on a warm 2-core machine, ~7 s on a fresh GPU machine) before the call itself begins
_IMPORTED = {}
IMPORT_THEN_CALL_S = 0.5  # an import that ended this shortly before a call was that call's own


def call_started(name: str, now: float) -> float:
    """When a call of the exported ``name`` that begins at ``now`` started for its caller: the start of its own
    first-use import when that import has just ended (``ngf.train(...)`` in a fresh process), else ``now``.
    Budgets count from there, so a budgeted call ends within its budget as the caller times it."""
    span = _IMPORTED.pop(name, None)
    if span is not None and 0.0 <= now - span[1] <= IMPORT_THEN_CALL_S:
        return span[0]
    return now


def lazy_exports(package: str, exports: dict, namespace: dict, listed=()):
    """(``__getattr__``, ``__dir__``) for ``package``: name -> submodule (relative to ``package``) in ``exports``;
    a name is imported on first access and kept in ``namespace`` (the package's globals)."""

    def __getattr__(name: str):
        module = exports.get(name)
        if module is None:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        t0 = time.perf_counter()
        value = getattr(importlib.import_module(f"{package}.{module}"), name)
        _IMPORTED[name] = (t0, time.perf_counter())
        namespace[name] = value
        return value

    def __dir__():
        return sorted(set(namespace) | set(exports) | set(listed))

    return __getattr__, __dir__
