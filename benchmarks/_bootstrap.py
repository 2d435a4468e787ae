"""Import ``neurogf_warp`` from this checkout, installed or not. Every benchmark imports this module first.

The package's kernels live in the top-level ``kernels/`` folder and only an install maps them to
``neurogf_warp.kernels``; here the mapping is made directly, so that this checkout wins over any installed copy.

    python benchmarks/_bootstrap.py MODULE [ARGS...]    # run MODULE as __main__ with this checkout's package
                                                       # (how benchmarks start torchrun workers)
"""
from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _origin(module) -> Path:
    return Path(getattr(module, "__file__", None) or "/").resolve()


def _use_checkout() -> None:
    mods = sys.modules
    if "neurogf_warp" in mods and _origin(mods["neurogf_warp"]) != ROOT / "neurogf_warp" / "__init__.py":
        for name in [n for n in mods if n == "neurogf_warp" or n.startswith("neurogf_warp.")]:
            del mods[name]  # a copy from another folder, imported before this module: replace it
    if str(ROOT) in sys.path:
        sys.path.remove(str(ROOT))
    sys.path.insert(0, str(ROOT))  # first, ahead of any install
    import neurogf_warp

    if "neurogf_warp.kernels" in mods and _origin(mods["neurogf_warp.kernels"]) == ROOT / "kernels" / "__init__.py":
        return
    # registered by hand: a finder of an install elsewhere must not supply the kernels or their submodules,
    # which are then found through this module's __path__ (ROOT/kernels)
    for name in [n for n in mods if n == "neurogf_warp.kernels" or n.startswith("neurogf_warp.kernels.")]:
        del mods[name]
    spec = importlib.util.spec_from_file_location("neurogf_warp.kernels", ROOT / "kernels" / "__init__.py",
                                                  submodule_search_locations=[str(ROOT / "kernels")])
    kernels = importlib.util.module_from_spec(spec)
    mods["neurogf_warp.kernels"] = kernels
    spec.loader.exec_module(kernels)
    neurogf_warp.kernels = kernels


_use_checkout()

if __name__ == "__main__":
    import runpy

    if len(sys.argv) < 2:
        sys.exit(f"usage: python {sys.argv[0]} MODULE [ARGS...]")
    sys.argv = sys.argv[1:]
    runpy.run_module(sys.argv[0], run_name="__main__", alter_sys=True)
