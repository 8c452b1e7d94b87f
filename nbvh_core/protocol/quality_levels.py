"""Named quality levels: image MSE targets of the paper's metric (`metrics.evaluate`), the one table the CLI, the
API, compress.py and the add-on's panel read. Plain Python (no torch): the add-on imports it."""
from __future__ import annotations

#: name -> image MSE the model must reach (lower = better). Each is what its fixed preset reached on the Stanford
#: bunny (an organic scan, the typical asset) at the preset's own budget, rounded up (bench/results/compact.csv:
#: preview 0.00078 in 60 s, default 0.00039 in 200 s, high 0.00024 in 600 s): the default level asks for the
#: quality the default preset gave. At 0.01 (the earlier "standard") a 1,000-triangle decimation met the level on
#: the bunny and the spiky sphere (4.4 KB and 8 KB as compact meshes): a level that loose never needs a model.
QUALITY_LEVELS = {"preview": 0.001, "standard": 0.0005, "high": 0.00025}
#: The level a run is sized to when it names no preset, size or target (CLI, compress.py, batches, the add-on).
DEFAULT_LEVEL = "standard"

#: A quality target costs at most this many trainings: the predicted size, then corrections (`decision.size_search`);
#: the add-on's ETA and the panel's time-limit hint say so.
TARGET_TRAININGS = 3


def most_trainings(settings: dict) -> int:
    """How many trainings a run of these settings (a request's dict) may take: TARGET_TRAININGS for a target with
    size_search "retrain", else 1 (a fixed size, a byte budget, or the default growing training)."""
    retrain = settings.get("size_search") == "retrain"
    return TARGET_TRAININGS if settings.get("target_mse") is not None and retrain else 1


def describe() -> str:
    """'preview = MSE 0.001, standard = 0.0005, high = 0.00025' (for help texts)."""
    items = list(QUALITY_LEVELS.items())
    return ", ".join(f"{name} = {'MSE ' if i == 0 else ''}{mse:g}" for i, (name, mse) in enumerate(items))
