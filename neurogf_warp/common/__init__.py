"""Shared plumbing of every stage: array conversion between numpy, torch and Warp, atomic file writes."""
