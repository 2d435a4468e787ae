"""Register caps on the solver's big kernels: python .bm/regs.py OUT.json RELAX DECODE (0: no cap)."""
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import gt_lanes as g  # noqa: E402  (maps the checkout's kernels, builds the meshes)

from neurogf_warp.kernels.ground_truth import relax  # noqa: E402
from neurogf_warp.mesh.mesh import load_mesh  # noqa: E402

out, r_relax, r_decode = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
for k, r in ((relax.relax_frontier, r_relax), (relax.decode_touched, r_decode)):
    if r:
        k.options["cuda_max_registers"] = r
g.OUT["regs"] = [r_relax, r_decode]
g.out_path = out
q = load_mesh(g.qslim436())
for name, m in (("q436K", q), ("bunny2.2M", load_mesh(g.bunny(3)))):
    g.rate(name, m, regs=(r_relax, r_decode))
