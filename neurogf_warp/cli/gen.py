"""The generalizable NeuroGF's commands: ``gen-shapes``, ``gen-train``, ``gen-per-mesh``.

``gen-train`` and ``gen-per-mesh`` are the command-line programs of ``generalizable.train`` and
``generalizable.per_mesh`` (also run under torchrun), shown under this program's name. ``gen-shapes`` is built
here; it imports nothing heavier than trimesh.
"""
from __future__ import annotations

import argparse
import sys

__all__ = ["GEN_COMMANDS", "run_gen", "shapes_parser"]

PROG = "neurogf-warp"

# name -> one line for `neurogf-warp -h`
GEN_COMMANDS = {
    "gen-shapes": "write a collection of generated shapes (train/ and test/ folders) for gen-train",
    "gen-train": "train a generalizable NeuroGF network on a folder of meshes (also under torchrun)",
    "gen-per-mesh": "train one per-mesh model for every mesh of a folder, spread over torchrun ranks",
}


def _integer_at_least(low: int):
    """An argparse type: an integer of at least ``low``."""
    def parse(text: str) -> int:
        try:
            v = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"not an integer: {text!r}") from None
        if v < low:
            raise argparse.ArgumentTypeError(f"must be {'0 or more' if low == 0 else f'at least {low}'}, got {v}")
        return v
    return parse


_nonnegative = _integer_at_least(0)
_positive = _integer_at_least(1)


def _test_every(text: str) -> int:
    v = _positive(text)
    if v < 2:  # 1 would put every shape into test/, leaving nothing to train on
        raise argparse.ArgumentTypeError(f"must be at least 2 (1 would leave no training shapes), got {v}")
    return v


def shapes_parser() -> argparse.ArgumentParser:
    """The parser of ``neurogf-warp gen-shapes``."""
    ap = argparse.ArgumentParser(
        prog=f"{PROG} gen-shapes",
        description="Write a collection of generated shapes as FOLDER/train/*.obj, FOLDER/test/*.obj and "
                    "FOLDER/manifest.json, the input of gen-train. Shape i depends only on (--seed, i), so a run "
                    "can be repeated or extended to a larger -n in the same folder; existing files are kept.")
    ap.add_argument("folder", help="output folder (created if missing)")
    ap.add_argument("-n", type=_positive, default=600, help="number of shapes, at least 1 (default 600)")
    ap.add_argument("--seed", type=_nonnegative, default=0, help="random seed of the collection (default 0)")
    ap.add_argument("--test-every", type=_test_every, default=10,
                    help="hold out every Nth instance of each shape family in test/ (default 10, at least 2)")
    ap.add_argument("--shared-meshes", default=None,
                    help="folder with the meshes the 'deformed' family bends (default: the test data's meshes "
                         "folder when it is found; without them those shapes are 'blob' instead)")
    ap.add_argument("--workers", type=_positive, default=1,
                    help="processes making shapes (default 1; the files are the same for any count)")
    return ap


def _cmd_shapes(argv) -> int:
    a = shapes_parser().parse_args(argv)
    import os

    from neurogf_warp.common.checks import InputError
    from neurogf_warp.generalizable.shapes import FAMILIES, is_test, write_collection

    if os.path.exists(a.folder) and not os.path.isdir(a.folder):
        raise InputError(f"{a.folder} is a file; give a folder for the collection")
    man = write_collection(a.folder, a.n, a.seed, a.test_every, a.shared_meshes, workers=a.workers)
    made = [man["shapes"][str(i)] for i in range(a.n)]
    n_test = sum(info["split"] == "test" for info in made)
    print(f"{PROG} gen-shapes: {a.n} shapes in {a.folder}: {a.n - n_test} in train/, {n_test} in test/",
          file=sys.stderr)
    if n_test == 0:
        first = next(i for i in range(10 ** 6) if is_test(i, a.test_every))
        print(f"{PROG} gen-shapes: no test split: a shape is held out when its instance number within its family "
              f"({len(FAMILIES)} families) is the last of every {a.test_every}, so the first is shape {first}; "
              f"use -n {first + 1} or more, or a smaller --test-every. Without test/ gen-train holds out every 10th "
              "file of the folder instead", file=sys.stderr)
    return 0


def _cmd_train(argv) -> int:
    from neurogf_warp.generalizable.train import main

    return main(argv, prog=f"{PROG} gen-train")


def _cmd_per_mesh(argv) -> int:
    from neurogf_warp.generalizable.per_mesh import main

    return main(argv, prog=f"{PROG} gen-per-mesh")


_RUN = {"gen-shapes": _cmd_shapes, "gen-train": _cmd_train, "gen-per-mesh": _cmd_per_mesh}


def run_gen(command: str, argv) -> int:
    """Run ``neurogf-warp COMMAND argv...`` for one of ``GEN_COMMANDS``; returns the exit code."""
    return _RUN[command](list(argv))
