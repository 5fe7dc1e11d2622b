"""The run report: its content (``content``, ``sections``), figures, and the HTML and PDF writers.

``stages.report`` assembles the sections from the saved artifacts and writes both formats.
"""
