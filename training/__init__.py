"""Procedural dataset, cross-solver ground truth, training loop, evaluation and baselines."""
