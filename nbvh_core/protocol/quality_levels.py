"""Named quality levels: image MSE targets of the paper's metric (`metrics.evaluate`), the one table the CLI, the
API, compress.py and the add-on's panel read. Plain Python (no torch): the add-on imports it."""
from __future__ import annotations

#: name -> image MSE the model must reach (lower = better).
QUALITY_LEVELS = {"preview": 0.02, "standard": 0.01, "high": 0.005}

#: A quality target costs at most this many trainings: the predicted size, then corrections (`sizing.next_size`);
#: the add-on's ETA and the panel's time-limit hint say so.
TARGET_TRAININGS = 3


def describe() -> str:
    """'preview = MSE 0.02, standard = 0.01, high = 0.005' (for help texts)."""
    items = list(QUALITY_LEVELS.items())
    return ", ".join(f"{name} = {'MSE ' if i == 0 else ''}{mse:g}" for i, (name, mse) in enumerate(items))
