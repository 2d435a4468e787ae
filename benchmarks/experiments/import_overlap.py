"""Does importing torch._dynamo in a background thread while the ground truth is solved shorten a training call?

Every training call imports torch._dynamo (torch.optim's add_param_group is wrapped by torch._disable_dynamo,
which imports it on first use): ~2.1 s on the 2-core CPU in a bare process, ~4-6 s inside a GPU call's
calibration (RESULTS.md, sixteenth session). This measures, in one fresh process per row, `build_dataset(mesh, time_limit_s=T)` with and
without that import running in a thread started just before it, then the wait for the import to finish.

    python benchmarks/experiments/import_overlap.py MESH --device cuda:0 --limit 20 --repeats 3

Prints one line per row and a JSON list at the end (row, dataset seconds, sources solved, wait for the import).
Found (sixteenth session): on the 2-core CPU the thread took ~20% of a 20 s build's sources (its worker processes
use both cores); on the GPU machine, tried inside `train()`, the bunny's 60 s call spent the import's seconds in a
longer ground-truth build instead (the GIL): not adopted.
"""
import argparse
import json
import subprocess
import sys
from pathlib import Path

BENCH = Path(__file__).resolve().parents[1]

ROW = r"""
import sys, time, threading, importlib, json
overlap = sys.argv[1] == "thread"
t0 = time.perf_counter()
sys.path.insert(0, sys.argv[5])
import time_to_accuracy  # the checkout's package, kernels mapped as an install maps them
time_to_accuracy._import_from_checkout()
from neurogf_warp.dataset.build import build_dataset
th = None
if overlap:
    th = threading.Thread(target=importlib.import_module, args=("torch._dynamo",), daemon=True)
    th.start()
t1 = time.perf_counter()
ds = build_dataset(sys.argv[2], None, device=sys.argv[3], progress=False, time_limit_s=float(sys.argv[4]))
t2 = time.perf_counter()
if th is not None:
    th.join()
import torch._dynamo  # noqa: F401  (the eager path's import: free if the thread did it)
t3 = time.perf_counter()
print(json.dumps({"row": sys.argv[1], "dataset_s": t2 - t1, "sources": int(len(ds.gd_src)), "import_wait_s": t3 - t2, "total_s": t3 - t0}))
"""


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("mesh")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--limit", type=float, default=20.0, help="the dataset's time limit, seconds")
    ap.add_argument("--repeats", type=int, default=3)
    a = ap.parse_args()
    rows = []
    for _ in range(a.repeats):
        for mode in ("none", "thread", "thread", "none"):  # ABBA against drift
            out = subprocess.run([sys.executable, "-c", ROW, mode, a.mesh, a.device, str(a.limit), str(BENCH)],
                                 capture_output=True, text=True)
            if out.returncode:
                print(out.stderr[-2000:], file=sys.stderr)
                raise SystemExit(out.returncode)
            r = json.loads(out.stdout.strip().splitlines()[-1])
            print(f'{r["row"]:7s} dataset {r["dataset_s"]:6.2f} s  sources {r["sources"]:5d}  '
                  f'import wait {r["import_wait_s"]:5.2f} s  total {r["total_s"]:6.2f} s', flush=True)
            rows.append(r)
    print(json.dumps(rows))


if __name__ == "__main__":
    main()
