"""The model: scenario schema and validation, dynamics, geometry, simulation, demos."""
