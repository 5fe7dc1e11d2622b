"""The emitted controller flown in its model: simulation, sampled uncertainty, the compiled
rollouts' checks, the worst-case search, and a single flight."""
