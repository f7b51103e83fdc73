"""Solvers for stage-wise NLPs (nothing robot-specific)."""
