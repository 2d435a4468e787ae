"""Small entry points for the existing package (``ngf.load``, the command line) to reach this subpackage.

Kept here so that the hooks in the modules outside this subpackage stay one or two lines each.
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


def cli_train(argv) -> int:
    """``neurogf-warp gen-train FOLDER -o model.pt ...`` (same options as ``python -m ...generalizable.train``)."""
    from neurogf_warp.generalizable.train import main

    return main(argv)


def cli_shapes(argv) -> int:
    """``neurogf-warp gen-shapes FOLDER -n 600 --seed 0``: write a shape collection."""
    import argparse

    from neurogf_warp.generalizable.shapes import write_collection

    ap = argparse.ArgumentParser(prog="neurogf-warp gen-shapes", description="write a shape collection")
    ap.add_argument("folder")
    ap.add_argument("-n", type=int, default=600)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--test-every", type=int, default=10)
    ap.add_argument("--shared-meshes", default=None)
    ap.add_argument("--workers", type=int, default=1, help="processes making shapes (same files for any count)")
    a = ap.parse_args(argv)
    write_collection(a.folder, a.n, a.seed, a.test_every, a.shared_meshes, workers=a.workers)
    return 0


def cli_per_mesh(argv) -> int:
    """``neurogf-warp gen-per-mesh FOLDER -o OUTDIR ...``: one per-mesh model per mesh, spread over ranks."""
    from neurogf_warp.generalizable.per_mesh import main

    return main(argv)


CLI_COMMANDS = {"gen-train": cli_train, "gen-shapes": cli_shapes, "gen-per-mesh": cli_per_mesh}
