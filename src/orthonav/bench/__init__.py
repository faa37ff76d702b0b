"""Benchmarks: measured side by side in one run, printed as tables, written as JSON and PNG."""

from orthonav.bench.localize import LocalizeBenchConfig, run_localize_benchmark

__all__ = ["LocalizeBenchConfig", "run_localize_benchmark"]
