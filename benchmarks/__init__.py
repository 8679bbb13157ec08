"""Benchmarks (not tests): run ``python -m benchmarks.<name>``; results go to benchmarks/results/."""
