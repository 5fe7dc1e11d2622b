"""The constant certificate ``(P, K, lambda)``: the contraction inequality (C), the tube's
geometry and radius, zero-order hold, and the search that tunes the feedback design."""
