"""Stage 5, inference: the public queries, their input checks, per-device state and the tensor-core engine."""
