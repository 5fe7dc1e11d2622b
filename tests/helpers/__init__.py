"""Helpers shared by several test modules (``from tests.helpers.<topic> import ...``).

A test module imports helpers from here, never from another test module or a conftest.py.
"""
