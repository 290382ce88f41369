"""matplotlib for files only: the Agg backend, chosen before pyplot is first imported."""
from __future__ import annotations


def pyplot():
    """matplotlib.pyplot on the Agg backend (ImportError when the plot extra is missing)."""
    import matplotlib  # imported on first use: the plot extra is optional

    matplotlib.use("Agg")  # files only, no display: must come before pyplot is imported
    import matplotlib.pyplot as plt

    return plt
