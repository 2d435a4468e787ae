"""Warp kernels of the queries: the fused fp16 tensor-core engine (native/), the per-thread float32 network and
its gradients, distance finishing, path refinement."""
