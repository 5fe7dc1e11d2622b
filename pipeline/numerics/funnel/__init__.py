"""The funnel: per-trajectory gains ``K[k]`` and metrics ``P[k]`` at a level ``rho`` (the law,
its enclosures, pieces, semidefinite program, synthesis, and the check of (F1)-(F3))."""
