"""One picture of a geodesic distance field on a mesh: a NeuroGF's, the exact one, or the heat method's.

    python examples/render_field.py MODEL --mesh MESH --source V [V ...] -o picture.png [--paths K]

The arguments follow ``neurogf-warp render``; the extra ``--exact REF.npz`` and ``--heat`` draw the exact
(MMP reference file, see shared/reference/README.md) or heat-method (potpourri3d) field from the same
sources instead of the model's, with paths from our geodesic solver (``--exact``) or potpourri3d's edge-flip
solver (``--heat``). One source gives SSAD, several the distance to the nearest (MSAD). Paths run from the
first source to ``--targets`` (default: K vertices drawn with --seed). ``--vrange`` fixes the colour scale,
so that pictures of the same sources can be compared.
"""
from __future__ import annotations

import argparse
import time

import numpy as np

import neurogf_warp as ngf


def reference_index(z, mesh) -> np.ndarray:
    """The reference file's vertices in the mesh's numbering: its ``file_index`` (the file's vertex records) or
    ``orig_index`` (trimesh's order), whichever puts its positions on the mesh's vertices."""
    pos = z["positions"]
    for key in ("file_index", "orig_index"):
        idx = z[key].astype(np.int64) if key in z.files else None
        try:
            if idx is not None and np.abs(mesh.vertices[mesh.vertex(idx)] - pos).max() <= 1e-5 * np.abs(pos).max():
                return idx
        except IndexError:  # that numbering does not fit this mesh
            pass
    raise SystemExit("the reference file's vertices do not match this mesh")


def exact_field(ref_path, mesh, sources):
    """Exact distances to the nearest source from a reference .npz, one per vertex in the mesh's numbering."""
    z = np.load(ref_path)
    idx = reference_index(z, mesh)
    rows = []
    for s in sources:
        hit = np.flatnonzero(idx[z["sources"]] == s)
        if not len(hit):
            raise SystemExit(f"source {s} is not a source of {ref_path}: it has {list(idx[z['sources']])}")
        rows.append(z["dist"][hit[0]].astype(np.float64))
    out = np.full(mesh.n_input, np.nan)
    out[idx] = np.min(rows, axis=0)
    return out


def heat_field(mesh, sources):
    import potpourri3d as pp3d

    solver = pp3d.MeshHeatMethodDistanceSolver(mesh.vertices, mesh.faces.astype(np.int64))
    d = solver.compute_distance_multisource([int(i) for i in mesh.vertex(sources)])
    return mesh.to_input(d)


def edge_flip_paths(mesh, source, targets):
    import potpourri3d as pp3d

    solver = pp3d.EdgeFlipGeodesicSolver(mesh.vertices, mesh.faces.astype(np.int64))
    s = int(mesh.vertex([source])[0])
    return [solver.find_geodesic_path(s, int(t)) for t in mesh.vertex(targets)]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("model", help="model file (.ngf, or a released *_final.pth with --mesh)")
    ap.add_argument("--mesh", help="the model's mesh (needed for a released .pth)")
    ap.add_argument("--source", type=int, nargs="+", required=True, help="source vertices (the mesh's numbering)")
    ap.add_argument("-o", "--output", required=True, help="picture file (.png)")
    ap.add_argument("--paths", type=int, default=0, metavar="K", help="draw K shortest paths from the first source")
    ap.add_argument("--targets", type=int, nargs="+", help="path targets (default: K vertices drawn with --seed)")
    ap.add_argument("--refine", type=int, default=0, help="shortening sweeps for the model's paths (path(refine=))")
    field = ap.add_mutually_exclusive_group()
    field.add_argument("--exact", metavar="REF.npz", help="draw the exact field of this reference file instead")
    field.add_argument("--heat", action="store_true", help="draw the heat method's field (potpourri3d) instead")
    ap.add_argument("--size", type=int, nargs=2, default=(640, 640), metavar=("W", "H"))
    ap.add_argument("--view", type=float, nargs=2, default=None, metavar=("AZIMUTH", "ELEVATION"))
    ap.add_argument("--isolines", type=int, default=20)
    ap.add_argument("--vrange", type=float, nargs=2, default=None, metavar=("LOW", "HIGH"))
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--device", default=None)
    a = ap.parse_args(argv)

    import warp as wp

    wp.config.log_level = wp.LOG_WARNING
    t0 = time.perf_counter()
    model = ngf.load(a.model, mesh=a.mesh)
    mesh = model.mesh
    if a.exact:
        values, what = exact_field(a.exact, mesh, a.source), "exact"
    elif a.heat:
        values, what = heat_field(mesh, a.source), "heat method"
    else:
        values = (ngf.ssad(model, a.source[0], device=a.device) if len(a.source) == 1
                  else ngf.msad(model, a.source, device=a.device))
        what = "NeuroGF"
    paths = None
    if a.paths:
        targets = a.targets or [int(t) for t in mesh.index[np.random.default_rng(a.seed).choice(
            len(mesh.vertices), a.paths, replace=False)]]
        targets = targets[:a.paths]
        if a.exact:
            paths = ngf.geodesic_paths(mesh, a.source[0], targets, m=128, device=a.device)
        elif a.heat:
            paths = edge_flip_paths(mesh, a.source[0], targets)
        else:
            p = np.repeat(mesh.vertices[mesh.vertex(a.source[:1])], len(targets), 0)
            paths = ngf.path(model, p, mesh.vertices[mesh.vertex(targets)], m=128, refine=a.refine, device=a.device)
    ngf.render(model, values, sources=a.source, paths=paths, isolines=a.isolines, out=a.output, size=tuple(a.size),
               view=None if a.view is None else tuple(a.view), vrange=a.vrange, device=a.device)
    print(f"{a.output}: {what} field from {len(a.source)} source(s), {a.paths} path(s), "
          f"{time.perf_counter() - t0:.1f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
