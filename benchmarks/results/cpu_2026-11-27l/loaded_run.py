import time, sys, warnings
t0 = time.perf_counter()
import neurogf_warp as ngf
m = ngf.train("/work/shared/meshes/fandisk.obj", "/tmp/s12/loaded/f.ngf", budget_seconds=float(sys.argv[1]), device="cpu", force=True, progress=False)
print("call", round(time.perf_counter() - t0, 2), "val", m.config.get("validation_mre"), "heat", m.config.get("heat_mre"), "warn", m.config.get("quality_warning"), m.config.get("budget_warning"))
