"""One batch of 32 sources on the 436K mesh from the host loop (no graph), for ncu to pick launches from."""
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
sys.path.insert(0, str(Path(__file__).resolve().parent))
import time_to_accuracy as tta  # noqa: E402

tta._import_from_checkout()
import numpy as np  # noqa: E402
import warp as wp  # noqa: E402

import gt_lanes as g  # noqa: E402  (meshes)
import neurogf_warp.ground_truth.solver as S  # noqa: E402
from neurogf_warp.mesh.mesh import load_mesh  # noqa: E402

q = load_mesh(g.qslim436())
sol = S.GeodesicSolver(q, device="cuda:0", batch=32)
sol._graphs = {"start": False, "loop": False, "finish": False}
sol.run(np.random.default_rng(1).choice(sol.nv, 32, replace=False))
wp.synchronize()
print("iterations", sol.timings["iterations"][-1])
