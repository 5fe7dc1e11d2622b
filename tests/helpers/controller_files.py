"""Edits of a ``controller.json`` document, for the tests that check a broken file is caught."""

from __future__ import annotations

import numpy as np


def scale_gains(document: dict, factor: float) -> None:
    """Every gain of a controller.json scaled by ``factor``: the constant ``feedback.K``
    (safety-controller/1) or each trajectory's ``K[k]`` (/2)."""
    holders = [document["feedback"]] if "K" in document.get("feedback", {}) else []
    for holder in holders or document["trajectories"]:
        holder["K"] = (factor * np.array(holder["K"])).tolist()
