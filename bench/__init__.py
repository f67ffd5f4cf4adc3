"""Benchmark scripts (not installed with the package): one per issue, and ``run_all`` for all of them."""
