"""Run benchmarks/geodesics.py of the checkout two folders up, with neurogf_warp.kernels mapped from kernels/."""
import runpy
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
import time_to_accuracy as tta  # noqa: E402

tta._import_from_checkout()
sys.argv = [str(ROOT / "benchmarks" / "geodesics.py")] + sys.argv[1:]
runpy.run_path(sys.argv[0], run_name="__main__")
