import sys
sys.path.insert(0, 'benchmarks')
import time_to_accuracy
time_to_accuracy._import_from_checkout()
from neurogf_warp.dataset import build as D
D.build_dataset("/tmp/bt/meshes/homer.obj", None, n_sources=64, n_path_sources=64, device="cuda:0", progress=False)
print("warm")
