"""The README's pictures: the released bunny NeuroGF's SSAD, MSAD (5 sources) and paths next to the exact
field and the heat method's, each made by one ``examples/render_field.py`` command (printed as it runs).

    python examples/readme_pictures.py [--shared ../shared] [--out docs/pictures] [--size 512]

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
    ap.add_argument("--shared", default=str(HERE.parents[1] / "shared"), help="the shared test-data folder")
    ap.add_argument("--out", default=str(HERE.parent / "docs" / "pictures"))
    ap.add_argument("--size", type=int, default=512)
    ap.add_argument("--device", default=None)
    a = ap.parse_args(argv)
    import render_field  # noqa: E402  (beside this file)

    sh = Path(a.shared)
    model = sh / "checkpoints" / "official" / "NeuroGF_Pretrainer__bunny_final.pth"
    mesh = sh / "meshes" / "stanford-bunny.obj"
    ref = sh / "reference" / "exact" / "stanford-bunny.npz"
    import neurogf_warp as ngf

    z = np.load(ref)
    m = ngf.load_mesh(mesh)
    idx = render_field.reference_index(z, m)
    src = [int(s) for s in idx[z["sources"]]]  # the reference's 8 sources, mesh numbering
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    ssad, msad = [src[1]], [src[0], src[1], src[2], src[3], src[7]]
    targets = ["--targets", *map(str, [src[2], src[3], src[0], m.index[1000], m.index[20000]])]

    def hi(sources):
        rows = [z["dist"][src.index(s)] for s in sources]
        return f"{float(np.min(rows, axis=0).max()):.6g}"

    jobs = []
    for name, sources, extra in (("ssad", ssad, []), ("msad", msad, []), ("paths", ssad, ["--paths", "5", *targets])):
        common = [str(model), "--mesh", str(mesh), "--source", *map(str, sources), "--size", str(a.size), str(a.size),
                  "--vrange", "0", hi(sources), *extra, *(["--device", a.device] if a.device else [])]
        jobs.append(common + ["-o", str(out / f"bunny_{name}_neurogf.png")])
        if name == "paths":
            jobs.append(common + ["--refine", "50", "-o", str(out / f"bunny_{name}_neurogf_refined.png")])
        jobs.append(common + ["--exact", str(ref), "-o", str(out / f"bunny_{name}_exact.png")])
        if name != "paths":
            jobs.append(common + ["--heat", "-o", str(out / f"bunny_{name}_heat.png")])
    for args in jobs:
        print("python examples/render_field.py " + " ".join(shlex.quote(x) for x in args))
        render_field.main(args)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
