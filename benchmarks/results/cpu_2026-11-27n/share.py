# usage: python share.py SHARE MESH BUDGET OUTDIR : time_to_accuracy with training/api.DATA_SHARE = SHARE
import sys
sys.argv, share = [sys.argv[0]] + sys.argv[2:], float(sys.argv[1])
mesh, budget, out = sys.argv[1:4]
sys.path.insert(0, "/work/main/benchmarks")
import neurogf_warp.training.api as api
api.DATA_SHARE = share
import time_to_accuracy as T
sys.argv = ["time_to_accuracy.py", "--device", "cpu", "--meshes", mesh, "--budgets", budget, "--out", out,
            "--work", out + "/work", "--path-refine", "50", "-q"]
T.main()
