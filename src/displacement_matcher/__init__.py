"""Displacement matching: optimal before/after correspondence, per-unit motion and damage."""
