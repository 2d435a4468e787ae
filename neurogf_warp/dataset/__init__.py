"""Stage 3, the dataset: ground-truth pairs, paths and SDF samples for training, cached on disk."""
