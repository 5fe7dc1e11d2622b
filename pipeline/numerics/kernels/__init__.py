"""numba kernels generated from the scenario's expressions."""
