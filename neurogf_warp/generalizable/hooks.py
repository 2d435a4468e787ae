"""Small entry points for the existing package (``ngf.load``) to reach this subpackage (the command line's are in
``neurogf_warp/cli/gen.py``).

Kept here so that the hooks in existing modules stay one or two lines each (see the report of issue 23).
"""
from __future__ import annotations


def load_if_generalizable(path, mesh=None):
    """For ``ngf.load``: None when ``path`` is not a generalizable-network file; otherwise the
    :class:`~neurogf_warp.generalizable.model.GeneralizableModel`, or, when ``mesh`` is given, the model already
    conditioned on that mesh (a :class:`~neurogf_warp.generalizable.model.Conditioned`)."""
    from neurogf_warp.generalizable.network import is_generalizable_file

    try:  # torch files are zip archives; anything else (an .ngf, a missing file) is left to the per-mesh loader
        with open(path, "rb") as f:
            if f.read(2) != b"PK":
                return None
    except OSError:
        return None
    if not is_generalizable_file(path):
        return None
    from neurogf_warp.generalizable.model import load

    model = load(path)
    return model.condition(mesh) if mesh is not None else model
