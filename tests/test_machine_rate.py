"""Budgets in work, not seconds (nbvh_core/planning/machine_rate.py): the size predictor reads a budget as the
training it buys on this machine, measured by a probe once per machine and kept in the user's cache."""
import math

import pytest

from nbvh_core.planning import machine_rate
from nbvh_core.planning.machine_rate import REFERENCE_SAMPLES_PER_S, reference_budget_s, rounded_ratio


def test_the_ratio_is_rounded_so_that_probe_noise_never_moves_a_prediction():
    ref = REFERENCE_SAMPLES_PER_S
    assert rounded_ratio(ref * 1.3) == rounded_ratio(ref * 0.75) == rounded_ratio(ref) == 1.0
    assert rounded_ratio(ref * 2.1) == 2.0 and rounded_ratio(ref * 64) == 64.0
    assert math.isclose(rounded_ratio(ref * 0.66), 2 ** -0.5) and math.isclose(rounded_ratio(ref * 1.6), 2 ** 0.5)
    assert rounded_ratio(float("nan")) == rounded_ratio(0.0) == 1.0


def test_a_faster_machine_is_predicted_as_a_longer_budget_within_the_fitted_range(sample_meshes):
    from nbvh_core.planning.mesh_measures import mesh_features
    from nbvh_core.planning.sizing import load_fit

    feats = mesh_features(sample_meshes["bunny"])
    here, twice = load_fit(), load_fit()
    twice.work_ratio = 2.0
    assert twice.predict_log_mse(11, feats, None, 100.0) == pytest.approx(here.predict_log_mse(11, feats, None, 200.0))
    assert twice.predict_log_mse(11, feats, None, 100.0) < here.predict_log_mse(11, feats, None, 100.0)
    # a card 64x faster: 200 s read as the fitted range's 600 s, never extrapolated to 12,800 s
    assert reference_budget_s(200.0, 64.0) == 600.0 and reference_budget_s(200.0, 0.5) == 100.0
    assert reference_budget_s(900.0, 4.0) == 900.0


def test_the_rate_is_probed_once_per_machine_and_cached(tmp_path, monkeypatch):
    monkeypatch.delenv("NBVH_WORK_RATIO", raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    probes = []
    monkeypatch.setattr(machine_rate, "probe_samples_per_s",
                        lambda device: probes.append(device) or 2.2 * REFERENCE_SAMPLES_PER_S)
    assert machine_rate.work_ratio("cpu") == 2.0 and probes == ["cpu"]
    assert machine_rate.work_ratio("cpu") == 2.0 and probes == ["cpu"]  # from the cache
    assert (tmp_path / "nbvh" / "work_rate.json").exists()
    monkeypatch.setenv("NBVH_WORK_RATIO", "4")
    assert machine_rate.work_ratio("cpu") == 4.0


def test_the_probe_measures_this_machine_s_training():
    rate = machine_rate.probe_samples_per_s("cpu")
    # the 2-core VM read 343k-356k leaf samples/s (REFERENCE_SAMPLES_PER_S); any machine trains at a positive rate
    assert 1e3 < rate < 1e9


def test_a_run_on_a_faster_machine_says_how_its_budget_is_read(sample_meshes, monkeypatch):
    from nbvh_core.planning.run_config import plan_run
    from nbvh_core.planning.settings import preset

    monkeypatch.setenv("NBVH_WORK_RATIO", "2")
    run = plan_run(preset("default").with_overrides(target_mse=0.0005), sample_meshes["bunny"])
    assert any("2x as fast" in n.text and "400 s" in n.text for n in run.notes), run.notes
    monkeypatch.setenv("NBVH_WORK_RATIO", "1")
    slower = plan_run(preset("default").with_overrides(target_mse=0.0005), sample_meshes["bunny"])
    assert slower.predicted_log_mse[11] > run.predicted_log_mse[11]
