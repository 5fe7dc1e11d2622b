"""Checks independent of the synthesis: a nominal in continuous time, the coverage of Init,
and a shipped file's trajectories re-verified from its data alone."""
