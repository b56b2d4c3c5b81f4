"""Prefect tasks: thin wrappers around omniscs functions that pass ids and paths, never tensors."""
