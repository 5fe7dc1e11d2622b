"""The results layer: what stages exchange, below reporting and above numerics.

``pipeline.results.stage`` declares a stage (``Stage``: name, function, inputs type, result
type); the result types live beside it here so that reporting and runtime read them without
importing a stage.
"""
