"""Benchmarks (``make bench``): ratios measured side by side in one run, never absolute claims.

Each module ``bench/bench_*.py`` exports ``run() -> None`` that prints its own table.
"""
