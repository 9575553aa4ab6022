"""Inverse fitting of the medium (extinction, albedo, phase function, height fog, light power) from target images:
a global search, then a noise-aware Gauss-Newton solver (`fitting.solver`, docs/fitting.md)."""
