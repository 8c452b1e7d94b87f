"""Budgets in work, not seconds (nbvh_core/planning/machine_rate.py): the size predictor reads a budget as the
training it buys on this machine, measured by a probe once per machine and kept in the user's cache."""
import math

import pytest
import torch

from nbvh_core.planning import machine_rate, probe
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
    monkeypatch.setattr(probe, "probe_samples_per_s",
                        lambda device, batch: probes.append(device) or 2.2 * REFERENCE_SAMPLES_PER_S)
    assert machine_rate.work_ratio("cpu") == 2.0 and probes == ["cpu"]
    assert machine_rate.work_ratio("cpu") == 2.0 and probes == ["cpu"]  # from the cache
    assert (tmp_path / "nbvh" / "work_rate.json").exists()
    monkeypatch.setenv("NBVH_WORK_RATIO", "4")
    assert machine_rate.work_ratio("cpu") == 4.0


def test_the_probe_measures_this_machine_s_training():
    rate = probe.probe_samples_per_s("cpu", 2048)
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


def test_a_card_s_batch_is_the_smallest_that_reaches_most_of_its_best_rate():
    from nbvh_core.planning.card_batch import pick_batch

    # launch-bound small steps, a plateau from 32k rays: 32k (>= 70% of the best) rather than the largest
    assert pick_batch({2048: 0.9e6, 8192: 3.4e6, 32768: 14e6, 131072: 19e6}) == 32768
    assert pick_batch({2048: 20e6, 8192: 21e6, 32768: 22e6, 131072: 22e6}) == 2048
    assert pick_batch({2048: 1e6, 8192: 2e6, 32768: 4e6, 131072: 8e6}) == 131072
    assert pick_batch({}) == pick_batch({2048: 0.0}) == 2048


def test_the_cpu_keeps_its_batch_and_a_card_probes_its_ladder_once(tmp_path, monkeypatch):
    from nbvh_core.planning import card_batch

    monkeypatch.delenv("NBVH_CARD_RAYS_PER_STEP", raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    probes = []
    monkeypatch.setattr(card_batch, "probe_ladder",
                        lambda device: probes.append(device) or {2048: 1e6, 8192: 4e6, 32768: 9e6, 131072: 10e6})
    assert card_batch.rays_per_step("cpu") == 2048 and probes == []
    monkeypatch.setattr("nbvh_core.training.train.pick_device", lambda name: torch.device("cuda"))
    monkeypatch.setattr(probe, "machine_key", lambda device: f"a card|{device}")
    assert card_batch.rays_per_step("auto") == 32768 and probes == ["cuda"]
    assert card_batch.rays_per_step("cuda") == 32768 and probes == ["cuda"]  # from the cache
    monkeypatch.setenv("NBVH_CARD_RAYS_PER_STEP", "8192")
    assert card_batch.rays_per_step("cuda") == 8192


def test_settings_leave_the_batch_to_the_device_unless_set(sample_meshes, monkeypatch):
    from nbvh_core.planning import run_config
    from nbvh_core.planning.settings import preset

    s = preset("default").with_overrides(n_max=64)
    assert s.rays_per_step is None and s.train_config().rays_per_step == 2048
    assert run_config.plan_run(s, sample_meshes["blob"]).training.rays_per_step == 2048  # no card here
    monkeypatch.setattr(run_config, "card_rays_per_step", lambda device: 32768)  # what a card's probe chose
    assert run_config.plan_run(s, sample_meshes["blob"]).training.rays_per_step == 32768
    fixed = s.with_overrides(rays_per_step=4096)
    assert run_config.plan_run(fixed, sample_meshes["blob"]).training.rays_per_step == 4096


def test_a_large_step_labels_in_fewer_steps_per_chunk():
    from nbvh_core.training.config import TrainConfig
    from nbvh_core.training.ray_batches import chunk_steps

    assert chunk_steps(TrainConfig()) == 32 and chunk_steps(TrainConfig(rays_per_step=512)) == 32
    assert chunk_steps(TrainConfig(rays_per_step=32768)) == 4 and chunk_steps(TrainConfig(rays_per_step=1 << 17)) == 4
    assert chunk_steps(TrainConfig(rays_per_step=64, label_steps=3)) == 3
