"""The agents test (tests/test_examples.py) over many seeds: how often each of its checks fails.

    python benchmarks/experiments/agents_sweep.py --seeds 300 1300

Each seed draws the test's case (a reference source of the released fandisk model as target, 12 start vertices,
steps of 0.025 of the bounding radius) and walks it on Warp's CPU device with examples/geodesic_agents.py. Prints
the failing seeds per check (arrival, at the target, one-step rise <= 3/4 step, on the surface within 1% of the
radius, walked length within 10% and one step of the exact geodesic) and the worst value of each margin.
About 0.5 s per seed on a 2-core CPU.
"""
import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
import neurogf_warp as ngf  # noqa: E402
from neurogf_warp.mesh.surface import snap_to_mesh  # noqa: E402
from tests.conftest import shared_path  # noqa: E402
from tests.test_examples import load_example  # noqa: E402


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", type=int, nargs=2, default=(0, 100), metavar=("FIRST", "END"))
    a = ap.parse_args(argv)
    ex = load_example()
    model = ngf.load(shared_path("checkpoints", "official", "NeuroGF_Pretrainer__fandisk_final.pth"),
                     mesh=shared_path("meshes", "fandisk.obj"))
    mesh = model.mesh
    ref = np.load(shared_path("reference", "exact", "fandisk.npz"))
    radius = float(np.linalg.norm(mesh.internal_vertices - mesh.internal_vertices.mean(0), axis=1).max())
    speed = 0.025 * radius
    fails = {"arrive": [], "at target": [], "rise": [], "surface": [], "walk": []}
    worst = {"rise / step": 0.0, "(walked - exact - step) / exact": -1.0, "off surface / radius": 0.0}
    t0 = time.time()
    for seed in range(*a.seeds):
        rng = np.random.default_rng(seed)  # the same draws, in the same order, as the test
        k = int(rng.integers(len(ref["sources"])))
        target = int(ref["orig_index"][ref["sources"][k]])
        rows = rng.choice(len(ref["orig_index"]), 12, replace=False)
        starts = mesh.internal_vertices[mesh.vertex(ref["orig_index"][rows])]
        exact = ref["dist"][k][rows].astype(np.float64)
        steps = int(np.ceil(exact.max() / speed * 1.3)) + 5
        xs, ds = ex.simulate(model, target, starts, steps, speed, "cpu")
        tv = mesh.internal_vertices[mesh.vertex([target])][0]
        checks = {"arrive": np.all(ds[-1] <= 0.5 * speed),
                  "at target": np.linalg.norm(xs[-1] - tv, axis=1).max() <= speed}
        rise = float(np.diff(ds, axis=0).max() / speed)
        p, _, _ = snap_to_mesh(mesh, xs.reshape(-1, 3), device="cpu")
        off = float(np.linalg.norm(p - xs.reshape(-1, 3), axis=1).max() / radius)
        walked = np.linalg.norm(np.diff(xs, axis=0), axis=2).sum(0) + np.linalg.norm(xs[-1] - tv, axis=1)
        over = float(((np.abs(walked - exact) - speed) / exact).max())
        checks.update({"rise": rise <= 0.75, "surface": off <= 0.01, "walk": over <= 0.10})
        for name, ok in checks.items():
            if not ok:
                fails[name].append(seed)
        for name, v in zip(worst, (rise, over, off)):
            worst[name] = max(worst[name], v)
    n = a.seeds[1] - a.seeds[0]
    print(f"{n} draws (seeds {a.seeds[0]}..{a.seeds[1] - 1}) in {time.time() - t0:.0f} s")
    for name, seeds in fails.items():
        print(f"  {name:10s} failed in {len(seeds)}" + (f": seeds {seeds[:20]}" if seeds else ""))
    print("  worst: " + ", ".join(f"{k} {v:.4f}" for k, v in worst.items()))


if __name__ == "__main__":
    main()
