"""Model no more than a scene needs: the verdict against the compact mesh, the budget-aware predictor, node counts
scaled to the mesh, the decimation found by bisection, and the checks that score what the evaluation scores."""
import dataclasses

import numpy as np
import pytest

from meshes import icosphere
from nbvh_core.geometry.exact import ExactTracer
from nbvh_core.planning.settings import preset
from nbvh_core.planning.sizing import (DECIMATE_REFINE, LOG2_RANGE, MeshFeatures, alternatives, assess,
                                       choose_table_and_nodes, load_fit, max_nodes_for, mesh_features, resolve)


def test_the_verdict_weighs_the_model_against_the_layout_asked_for():
    # A 1,280-triangle sphere: 56 KB as a plain ray tracer holds it, ~12 KB as a compact mesh; a 2^8 model with 255
    # nodes is ~45 KB: smaller than the plain mesh, larger than the compact one.
    mesh = icosphere(3)
    s = preset("default").with_overrides(log2_table=8, nodes=255)
    compact = assess(mesh, s)
    plain = assess(mesh, s.with_overrides(mesh_layout="plain"))
    assert compact.compact_bytes < compact.model_bytes < compact.resident["total"]
    assert compact.recommendation == "mesh" and not compact.worth_compressing and compact.layout == "compact"
    assert "compact mesh" in compact.message and "plain ray tracer" in compact.message
    assert plain.recommendation == "neural" and plain.worth_compressing and plain.layout == "plain"
    with pytest.raises(ValueError, match="mesh_layout"):
        assess(mesh, dataclasses.replace(s, mesh_layout="dgf"))


def test_the_decimation_is_the_smallest_tried_that_meets_and_is_bracketed(sample_meshes):
    mesh = sample_meshes["bunny"]
    target = 0.004
    alt = alternatives(mesh, target, views=4, resolution=64)
    dec, tried = alt["decimation"], alt["decimations_tried"]
    assert dec["mse"] <= target
    met = [t for t in tried if t["mse"] <= target]
    assert dec["requested_triangles"] == min(t["requested_triangles"] for t in met)
    missed_below = [t for t in tried if t["mse"] > target and t["requested_triangles"] < dec["requested_triangles"]]
    assert missed_below, "the bisection needs a size that missed below the one kept"
    # The bracket around the kept size is within 2^(2 / 2^DECIMATE_REFINE) (x4 steps bisected in log space).
    gap = dec["requested_triangles"] / max(t["requested_triangles"] for t in missed_below)
    assert gap <= 2 ** (2 / 2 ** DECIMATE_REFINE) * 1.02
    assert len(tried) > 2


def test_the_predictor_expects_less_error_from_a_longer_budget_and_more_from_larger_tables():
    fit = load_fit()
    assert fit.budget_coef and len(fit.budget_coef) == 2
    f = MeshFeatures(triangles=100_000, area=3.0, occupancy=0.1, roughness=0.2)
    for l2 in LOG2_RANGE:
        assert fit.predict_log_mse(l2, f, budget_s=200) < fit.predict_log_mse(l2, f, budget_s=60) \
            < fit.predict_log_mse(l2, f, budget_s=fit.train_s) == pytest.approx(fit.predict_log_mse(l2, f))
    # The gain from 60 s to 200 s is larger for a larger table (an undertrained table has more to learn).
    gain = [fit.predict_log_mse(l2, f, budget_s=60) - fit.predict_log_mse(l2, f, budget_s=200) for l2 in (8, 13)]
    assert gain[1] > gain[0]
    # So a longer budget never asks for a larger table.
    size_of = lambda l2, n: (l2, n)  # noqa: E731
    assert choose_table_and_nodes(fit, f, 0.001, size_of, 600)[0] <= choose_table_and_nodes(fit, f, 0.001, size_of, 60)[0]


def test_node_counts_follow_the_mesh():
    assert max_nodes_for(100) == 255 and max_nodes_for(3072) == 511 and max_nodes_for(10**7) == 4095
    counts = [max_nodes_for(t) for t in (1000, 5000, 20000, 100000)]
    assert counts == sorted(counts)
    mesh = icosphere(3)  # 1,280 triangles: 255 nodes (5 triangles per leaf), not the fit's 2,047
    s, _ = resolve(preset("default").with_overrides(target_mse=0.0005), mesh)
    assert s.nodes == 255 and mesh_features(mesh).triangles == 1280


def test_a_check_with_cached_reference_images_scores_exactly_as_the_evaluation(sample_meshes, sample_tracers):
    import torch

    from nbvh_core.geometry.bvh import build_bvh
    from nbvh_core.neural.model import NeuralBVH
    from nbvh_core.rendering.metrics import evaluate, reference_views

    mesh = sample_meshes["blob"]
    model = NeuralBVH(build_bvh(mesh, 63).nodes, preset("tiny").model_config(), mesh.transform)
    tracer = sample_tracers["blob"]
    ref = reference_views(tracer, 3, 32)
    with torch.no_grad():
        a = evaluate(model, tracer, 3, 32)[0]
        b = evaluate(model, tracer, 3, 32, reference=ref)[0]
    assert a.mse == b.mse and a.silhouette_iou == b.silhouette_iou and np.isfinite(a.mse)
    with pytest.raises(ValueError, match="reference views"):
        evaluate(model, tracer, 4, 32, reference=ref)


class _ScriptedCheck:
    """Stands in for pipeline._QualityCheck: returns the next scripted MSE."""

    def __init__(self, values):
        self.values = list(values)

    def mse(self, model) -> float:
        return self.values.pop(0)


def _model_at(log2: int):
    from types import SimpleNamespace

    return SimpleNamespace(cfg=SimpleNamespace(encoding=SimpleNamespace(log2_table=log2)))


def test_growth_follows_the_projection_to_the_end_of_the_budget(monkeypatch):
    """With the predictor's budget exponent one check decides: MSE x (budget / now)^slope against the target; the
    early stop is below EARLY_STOP_MARGIN x the target; nothing grows at the top size; without an exponent two
    checks at a size give the power law, and a check without progress grows."""
    import nbvh_core.app.pipeline as pl

    now = [0.0]
    monkeypatch.setattr(pl.time, "perf_counter", lambda: now[0])
    target, budget = 1.0, 100.0
    # slope -0.5: at 25 s of 100 s an MSE falls by (100 / 25)^-0.5 = 0.5 by the end
    decide = pl._grow_check(_ScriptedCheck([1.9, 2.1, 0.5, 3.0]), target, 12, budget, lambda log2: -0.5)
    now[0] = 25.0
    assert decide(_model_at(10)) is False  # 0.95 at the end: met
    assert decide(_model_at(10)) == "grow"  # 1.05 at the end: missed
    assert decide(_model_at(11)) is True  # below 0.9 x the target now
    assert decide(_model_at(12)) is False  # the top size: nothing to grow to
    assert [c[1] for c in decide.history] == [10, 10, 11, 12]

    now[0] = 0.0
    two_point = pl._grow_check(_ScriptedCheck([4.0, 2.0, 2.0, 2.5]), target, 12, budget)
    now[0] = 10.0
    assert two_point(_model_at(10)) is False  # one check: no law yet
    now[0] = 20.0
    assert two_point(_model_at(10)) is False  # 4 -> 2 from 10 s to 20 s: slope -1, 0.4 at 100 s
    now[0] = 30.0
    assert two_point(_model_at(11)) is False  # the first check at the grown size
    now[0] = 40.0
    assert two_point(_model_at(11)) == "grow"  # worse than before: no progress at this size
