"""The released NeuroGF checkpoints through this package's Warp kernels: MRE against exact geodesics.

    python benchmarks/released.py --device cpu                     # fp32; fp16 fandisk in the CPU emulation
    python benchmarks/released.py --device cuda:0                  # fp32 and fp16 (tensor cores), both meshes

For the released bunny and fandisk checkpoints (``checkpoints/official/NeuroGF_Pretrainer__<mesh>_final.pth``,
loaded with their meshes) and every source of the exact references (``reference/exact/<mesh>.npz``: 8 sources,
every vertex), ``ngf.ssad`` in each precision against the exact distances: mean, p99 and max relative error, the
source vertex excluded. On the CPU, ``precision="fp16"`` runs the tensor-core code in a per-fiber emulation
(slow: ``--fp16-meshes`` picks the meshes, default fandisk there, both on a GPU). Writes ``--json``.
"""
from __future__ import annotations

import argparse
import sys
import time

import numpy as np

import _bootstrap  # noqa: F401  (this checkout's neurogf_warp, installed or not)
from common import find_shared, write_json

MESHES = {"bunny": ("stanford-bunny.obj", "stanford-bunny.npz"), "fandisk": ("fandisk.obj", "fandisk.npz")}


def released_mre(device: str, precisions: dict, quiet: bool = False) -> list:
    """Rows ``{mesh, precision, mre, p99, max, sources, pairs, seconds}`` for each mesh and its precisions.

    Parameters
    ----------
    device : str
        ``"cpu"`` or ``"cuda:N"``.
    precisions : dict
        Mesh name (``"bunny"``, ``"fandisk"``) -> tuple of precisions (``"fp32"``, ``"fp16"``).
    """
    import neurogf_warp as ngf
    from neurogf_warp.evaluation.evaluate import load_reference

    rows = []
    for name, precs in precisions.items():
        mesh_file, ref_file = MESHES[name]
        model = ngf.load(find_shared("checkpoints", "official", f"NeuroGF_Pretrainer__{name}_final.pth"),
                         mesh=find_shared("meshes", mesh_file))
        vids, sids, gt = load_reference(find_shared("reference", "exact", ref_file), model.mesh)
        for prec in precs:
            t = time.perf_counter()
            rel = []
            for i, s in enumerate(sids):
                d = ngf.ssad(model, int(model.mesh.index[s]), device=device, precision=prec)
                pred = d[model.mesh.index[vids]]  # mesh units, as load_reference gives the exact distances
                ok = np.isfinite(gt[i]) & (gt[i] > 0)
                rel.append(np.abs(pred[ok] - gt[i][ok]) / gt[i][ok])
            rel = np.concatenate(rel)
            row = {"mesh": name, "precision": prec, "mre": float(rel.mean()), "p99": float(np.quantile(rel, 0.99)),
                   "max": float(rel.max()), "sources": len(sids), "pairs": int(rel.size),
                   "seconds": time.perf_counter() - t}
            rows.append(row)
            if not quiet:
                print(f"released {name}, {prec}: MRE {row['mre']:.4%}, p99 {row['p99']:.3%}, max {row['max']:.3%} "
                      f"({row['pairs']:,} pairs, {row['seconds']:.1f} s)", flush=True)
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default=None, help="cpu or cuda:N (default: cuda:0 if there is one)")
    ap.add_argument("--fp16-meshes", nargs="*", default=None, choices=list(MESHES),
                    help="meshes to score in fp16 too (default: both on a GPU, fandisk on the CPU)")
    ap.add_argument("--json", default="released.json", help="output JSON (default: ./released.json)")
    a = ap.parse_args(argv)
    import torch

    device = a.device or ("cuda:0" if torch.cuda.is_available() else "cpu")
    fp16 = a.fp16_meshes if a.fp16_meshes is not None else (
        list(MESHES) if device.startswith("cuda") else ["fandisk"])
    rows = released_mre(device, {m: ("fp32", "fp16") if m in fp16 else ("fp32",) for m in MESHES})
    print(f"JSON: {write_json(a.json, {'rows': rows}, 'released', device)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
