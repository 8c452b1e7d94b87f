"""A scene's byte budget shared among its objects by need: every object gets the smallest table size predicted to
meet one common quality level (scaled by its weight), the level as strict as the budget allows. The prediction and
the bytes are handed in (`choose`, `bytes_for_log2`: `planning.sizing.plan_scene` makes them from the size
predictor and the settings), so the rule stays a rule on numbers."""
from __future__ import annotations

import math
from typing import Callable


def split_budget(n: int, budget_bytes: float, choose: Callable[[int, float], tuple[int, float]],
                 bytes_for_log2: Callable[[int, int], int], weights: list[float] | None = None) -> dict:
    """Share `budget_bytes` among `n` objects by need: object i gets choose(i, level / w_i) -> (log2 T, predicted
    MSE), the smallest size predicted to meet that level (w_i: its weight, e.g. share of the screen; bigger = needs
    to look better), with the common level as strict as the budget allows (bisection in log space).
    bytes_for_log2(i, log2) -> file bytes of object i's model. Returns {'level': MSE level, 'log2': [...],
    'bytes': [...], 'predicted_mse': [...], 'total': bytes, 'weights', 'budget'}; raises ValueError when even the
    smallest models do not fit the budget."""
    weights = [1.0] * n if weights is None else [max(float(w), 1e-6) for w in weights]

    def plan(level: float):
        l2s, sizes, preds = [], [], []
        for i in range(n):
            l2, pred = choose(i, level / weights[i])
            l2s.append(l2)
            sizes.append(bytes_for_log2(i, l2))
            preds.append(pred)
        return l2s, sizes, preds

    lo, hi = math.log(1e-6), math.log(1.0)  # strict .. loose
    best = None
    for _ in range(40):
        mid = (lo + hi) / 2
        l2s, sizes, preds = plan(math.exp(mid))
        if sum(sizes) <= budget_bytes:
            best = (math.exp(mid), l2s, sizes, preds)
            hi = mid  # fits: try stricter
        else:
            lo = mid
    if best is None:  # even the loosest level (every object at its smallest size) does not fit
        smallest = sum(plan(1.0)[1])
        raise ValueError(f"a budget of {budget_bytes / 1024:g} KB is too small for these {n} meshes: the smallest "
                         f"models need {smallest / 1024:.0f} KB together")
    level, l2s, sizes, preds = best
    return {"level": level, "log2": l2s, "bytes": sizes, "predicted_mse": preds, "total": int(sum(sizes)),
            "weights": weights, "budget": budget_bytes}
