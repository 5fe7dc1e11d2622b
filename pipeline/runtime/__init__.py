"""Orchestration, the stage cache and the command line (the only layer above stages)."""
