"""The ``neurogf-warp`` command: ssad | data | train | eval | demo."""
from __future__ import annotations

import argparse
import importlib
import os
import sys
import time

USAGE = """usage: neurogf-warp COMMAND [options]

commands:
  ssad    distances from one source vertex or point to every mesh vertex, with a trained model
  data    build a training dataset (ground-truth geodesics, paths, SDF samples) for a mesh
  train   train a NeuroGF model for a mesh
  eval    measure a model's accuracy against exact or solver geodesics
  demo    train on the bundled default mesh, report accuracy and answer an SSAD query

run 'neurogf-warp COMMAND -h' for a command's options"""


def _quiet_warp():
    import warp as wp

    wp.config.log_level = wp.LOG_WARNING


def ssad_main(argv) -> int:
    ap = argparse.ArgumentParser(prog="neurogf-warp ssad", description="Single-source geodesic distances to all vertices.")
    ap.add_argument("model", help="model file: our .ngf or a released NeuroGF *_final.pth")
    ap.add_argument("--mesh", help="the model's mesh (required for a released .pth; our files carry theirs)")
    src = ap.add_mutually_exclusive_group()
    src.add_argument("--source", type=int, default=0, help="source vertex index in the mesh's own numbering (default 0)")
    src.add_argument("--point", type=float, nargs=3, metavar=("X", "Y", "Z"), help="source point in mesh coordinates")
    ap.add_argument("-o", "--output", default="distances.npy", help="output .npy (one distance per mesh vertex)")
    ap.add_argument("--device", default=None, help="cpu or cuda:N (default: the GPU if there is one)")
    a = ap.parse_args(argv)
    _quiet_warp()
    import numpy as np

    import neurogf_warp as ngf
    from neurogf_warp.files import atomic_write

    model = ngf.load(a.model, mesh=a.mesh)
    src = np.array(a.point, dtype=np.float64) if a.point is not None else a.source
    t = time.perf_counter()
    d = ngf.ssad(model, src, device=a.device)
    first = time.perf_counter() - t
    t = time.perf_counter()
    d = ngf.ssad(model, src, device=a.device)
    again = time.perf_counter() - t
    atomic_write(a.output, lambda f: np.save(f, d))
    ok = np.isfinite(d)
    print(f"{model}: {ok.sum()} distances written to {a.output} "
          f"(min {np.nanmin(d):.6g}, max {np.nanmax(d):.6g}, mesh units); "
          f"first call {first:.2f} s (includes kernel compilation), second {again * 1e3:.1f} ms")
    return 0


# command -> (module, function taking argv)
COMMANDS = {
    "ssad": (".cli", "ssad_main"),
    "data": (".dataset", "data_main"),
    "train": (".train", "train_main"),
    "eval": (".evaluate", "eval_main"),
    "demo": (".demo", "demo_main"),
}


def main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] in ("-h", "--help"):
        print(USAGE)
        return 0 if argv else 2
    cmd, rest = argv[0], argv[1:]
    if cmd not in COMMANDS:
        print(f"neurogf-warp: unknown command {cmd!r}\n\n{USAGE}", file=sys.stderr)
        return 2
    try:
        _quiet_warp()
        module, func = COMMANDS[cmd]
        run = getattr(importlib.import_module(module, __package__), func)  # imported only when used
        return run(rest) or 0
    except (FileNotFoundError, PermissionError, ValueError, TypeError, IndexError) as e:
        if os.environ.get("NEUROGF_DEBUG"):
            raise
        print(f"neurogf-warp {cmd}: error: {e}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(f"neurogf-warp {cmd}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
