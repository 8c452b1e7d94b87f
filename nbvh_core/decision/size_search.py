"""The size search of a run with a quality target and size_search "retrain": predict a table size, train it,
measure it, correct (at most `max_trainings` trainings). The prediction is the size predictor's
(`planning.sizing.SizeFit`), handed in as `predict(log2 T) -> ln MSE` so the rule stays a rule on numbers."""
from __future__ import annotations

import math
from typing import Callable

from ..protocol.quality_levels import TARGET_TRAININGS

Predict = Callable[[int], float]


def next_size(predict: Predict | None, target_mse: float, measured: dict[int, float],
              sizes: range) -> int | None:
    """The next log2 T (in `sizes`) to train after measuring `measured` {log2 T: image MSE}, or None to stop.

    The predictor's error for a mesh is mostly an offset (its residuals are per mesh), so each measurement
    calibrates it: calibrated(T) = predicted(T) x measured(T0) / predicted(T0), T0 the last size trained.
    * Target missed everywhere so far: the smallest larger T whose calibrated MSE meets it (the largest in `sizes`
      when none is predicted to); None at the top of the range.
    * Target met: one step down (the largest smaller T, not yet trained) if its calibrated MSE meets it, else
      None; a smaller size that then misses ends the search (the smallest size that met is kept).
    Without a predictor: one step up when missed, no step down.
    """
    last = list(measured)[-1]
    met = [l2 for l2, mse in measured.items() if mse <= target_mse]
    if predict is None:
        return last + 1 if not met and last + 1 <= sizes[-1] else None
    offset = math.log(measured[last]) - predict(last)

    def calibrated_ok(l2: int) -> bool:
        return predict(l2) + offset <= math.log(target_mse)

    if not met:
        larger = [l2 for l2 in sizes if l2 > max(measured)]
        if not larger:
            return None
        # The smallest predicted to meet it; none predicted: the largest (the best chance there is).
        return next((l2 for l2 in larger if calibrated_ok(l2)), larger[-1])
    if measured[last] > target_mse:  # a step down missed: keep the smallest that met
        return None
    smaller = min(met) - 1
    if smaller < sizes[0] or smaller in measured or not calibrated_ok(smaller):
        return None
    return smaller


def search_size(predict: Predict | None, target_mse: float, first_log2: int, measure: Callable[[int], float],
                sizes: range, max_trainings: int = TARGET_TRAININGS) -> tuple[int, dict[int, float]]:
    """Train-and-measure search for the smallest log2 T meeting `target_mse`: `measure(log2) -> MSE` trains and
    scores one size (the expensive part); starts at `first_log2` (the predictor's choice) and follows `next_size`
    for at most `max_trainings` measurements. Returns (chosen log2 T, {log2 T: MSE} in the order measured): the
    smallest measured size that met the target, else the largest measured."""
    measured: dict[int, float] = {}
    l2: int | None = first_log2
    while l2 is not None and len(measured) < max_trainings:
        measured[l2] = measure(l2)
        l2 = next_size(predict, target_mse, measured, sizes)
    met = [t for t, mse in measured.items() if mse <= target_mse]
    return (min(met) if met else max(measured)), measured
