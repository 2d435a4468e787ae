"""Names a package exports and imports on first use, so that importing the package (and ``--help``) stays light."""
from __future__ import annotations

import importlib


def lazy_exports(package: str, exports: dict, namespace: dict, listed=()):
    """(``__getattr__``, ``__dir__``) for ``package``: name -> submodule (relative to ``package``) in ``exports``;
    a name is imported on first access and kept in ``namespace`` (the package's globals)."""

    def __getattr__(name: str):
        module = exports.get(name)
        if module is None:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        value = getattr(importlib.import_module(f"{package}.{module}"), name)
        namespace[name] = value
        return value

    def __dir__():
        return sorted(set(namespace) | set(exports) | set(listed))

    return __getattr__, __dir__
