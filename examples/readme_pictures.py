"""The README's pictures: the released bunny NeuroGF's SSAD, MSAD (5 sources) and paths next to the exact
field and the heat method's, each made by one ``neurogf-warp render`` command (printed as it runs).

    python examples/readme_pictures.py --out FOLDER [--shared ../shared] [--size 512]

It writes only into the folder you name (``--out docs/pictures`` remakes the README's own pictures).

The colour scale of each row is the exact field's range, so the three pictures of a row compare directly.
"""
from __future__ import annotations

import argparse
import shlex
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--shared", default=str(HERE.parents[1] / "shared"),
                    help="the shared test-data folder (default: ../shared beside the checkout)")
    ap.add_argument("--out", required=True, help="folder for the nine pictures (created if missing); "
                    "docs/pictures to remake the README's")
    ap.add_argument("--size", type=int, default=512, help="picture width and height in pixels (default 512)")
    ap.add_argument("--device", default=None, help="cpu or cuda:N (default: Warp's preferred device)")
    a = ap.parse_args(argv)
    from neurogf_warp.cli.main import main as cli

    sh = Path(a.shared)
    model = sh / "checkpoints" / "official" / "NeuroGF_Pretrainer__bunny_final.pth"
    mesh = sh / "meshes" / "stanford-bunny.obj"
    ref = sh / "reference" / "exact" / "stanford-bunny.npz"
    import neurogf_warp as ngf
    from neurogf_warp.evaluation.evaluate import load_reference

    z = np.load(ref)
    m = ngf.load_mesh(mesh)
    _, sids, _ = load_reference(ref, m)
    src = [int(s) for s in m.index[sids]]  # the reference's 8 sources, the mesh file's numbering
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    ssad, msad = [src[1]], [src[0], src[1], src[2], src[3], src[7]]
    targets = ["--paths", *map(str, [src[2], src[3], src[0], m.index[1000], m.index[20000]])]

    def hi(sources):
        rows = [z["dist"][src.index(s)] for s in sources]
        return f"{float(np.min(rows, axis=0).max()):.6g}"

    jobs = []
    for name, sources, extra in (("ssad", ssad, []), ("msad", msad, []), ("paths", ssad, targets)):
        common = [str(model), "--mesh", str(mesh), "--source", *map(str, sources), "--size", str(a.size), str(a.size),
                  "--vrange", "0", hi(sources), *extra, *(["--device", a.device] if a.device else [])]
        jobs.append(common + ["-o", str(out / f"bunny_{name}_neurogf.png")])
        if name == "paths":
            jobs.append(common + ["--refine", "50", "-o", str(out / f"bunny_{name}_neurogf_refined.png")])
        jobs.append(common + ["--exact", str(ref), "-o", str(out / f"bunny_{name}_exact.png")])
        if name != "paths":
            jobs.append(common + ["--heat", "-o", str(out / f"bunny_{name}_heat.png")])
    for args in jobs:
        print("neurogf-warp render " + " ".join(shlex.quote(x) for x in args), flush=True)
        if cli(["render", *args, "-q"]):
            return 1
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
