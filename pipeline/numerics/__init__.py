"""Numerical methods on the model: penalties, gradients, descent, hull, verification."""
