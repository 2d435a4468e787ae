"""Griffe extension for the API reference: document the top-level ``kernels/`` folder as ``neurogf_warp.kernels``.

pyproject's ``package-dir`` installs ``kernels/`` as the subpackage ``neurogf_warp.kernels``; griffe reads
packages from the source tree and would not find it there. This loads ``kernels`` beside ``neurogf_warp`` and
attaches it as the member ``kernels``, so ``::: neurogf_warp.kernels.field`` and references to it resolve.
"""
from __future__ import annotations

import griffe


class KernelsSubpackage(griffe.Extension):
    def on_package(self, *, pkg: griffe.Module, loader: griffe.GriffeLoader, **kwargs) -> None:
        if pkg.name != "neurogf_warp" or "kernels" in pkg.members:
            return
        kernels = loader.load("kernels", try_relative_path=False)
        # the same module object, now reached (and named) as neurogf_warp.kernels
        pkg.set_member("kernels", kernels)
