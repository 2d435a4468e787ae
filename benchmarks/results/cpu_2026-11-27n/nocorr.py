# usage: python nocorr.py MESH BUDGET OUTDIR : time_to_accuracy with the coarse-row correction off
import sys
mesh, budget, out = sys.argv[1:4]
sys.path.insert(0, "/work/main/benchmarks")
import neurogf_warp.dataset.build as D
D.COARSE_MAX_BIAS = -1.0  # no bias passes: scale 1
import time_to_accuracy as T
sys.argv = ["time_to_accuracy.py", "--device", "cpu", "--meshes", mesh, "--budgets", budget, "--out", out,
            "--work", out + "/work", "--path-refine", "50", "-q"]
T.main()
