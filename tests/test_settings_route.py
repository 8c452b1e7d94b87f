"""One route from a request to Settings, shared by the command line, the add-on's job and library batches."""
import pytest

from nbvh_core.planning.settings import preset, settings_from_request


def test_a_request_is_its_preset_with_the_fields_it_names():
    s = settings_from_request({"preset": "preview", "log2_table": 9, "seed": None})
    assert s.log2_table == 9 and s.nodes == preset("preview").nodes and s.seed == preset("preview").seed
    assert settings_from_request({"preset": "default"}) == preset("default")


def test_a_request_with_no_preset_and_no_size_is_sized_to_the_default_level():
    from nbvh_core.protocol.quality_levels import DEFAULT_LEVEL, QUALITY_LEVELS

    s = settings_from_request({})
    assert s.target_mse == QUALITY_LEVELS[DEFAULT_LEVEL] and s.size_search == "grow"
    assert s.time_limit_s == preset("default").time_limit_s and s.mesh_layout == "compact"
    # Anything that fixes a size (or a named preset) keeps it fixed.
    assert settings_from_request({"preset": "preview"}).target_mse is None
    assert settings_from_request({"budget_kb": 100}).target_mse is None
    assert settings_from_request({"log2_table": 9}).target_mse is None
    assert settings_from_request({"target_mse": 0.003}).target_mse == 0.003


def test_named_choices_are_checked_in_requests_and_files():
    from nbvh_core.planning.settings import settings_from_dict

    with pytest.raises(ValueError, match="size_search.*grow, retrain"):
        settings_from_dict({"size_search": "bogus"})
    with pytest.raises(ValueError, match="mesh_layout.*compact, plain"):
        settings_from_dict({"mesh_layout": "dgf"})


def test_time_limit_zero_means_a_budget_in_steps():
    s = settings_from_request({"preset": "default", "steps": 30, "time_limit_s": 0})
    assert s.steps == 30 and s.time_limit_s is None


def test_unknown_presets_and_fields_are_refused():
    with pytest.raises(ValueError, match="unknown preset"):
        settings_from_request({"preset": "fastest"})
    with pytest.raises(ValueError, match="unknown settings"):
        settings_from_request({"log2_tabel": 9})


def test_the_cli_job_and_batch_take_this_route():
    import ast
    from pathlib import Path

    app = Path(__file__).resolve().parents[1] / "nbvh_core" / "app"
    for name in ("cli_compress.py", "job.py", "library_batch.py"):
        calls = {n.func.id if isinstance(n.func, ast.Name) else getattr(n.func, "attr", "")
                 for n in ast.walk(ast.parse((app / name).read_text())) if isinstance(n, ast.Call)}
        assert "settings_from_request" in calls, name


def test_a_run_is_planned_once_into_parts_that_agree_with_its_request():
    """plan_run: every part says what the request says; a look takes its share of the budget from the geometry's
    training (the request keeps the budget asked); a table size (planned with a run that has a target) or a training
    knob changed changes both."""
    from nbvh_core.geometry.demo_assets import crate
    from nbvh_core.planning.run_config import plan_run

    from meshes import icosphere

    s = preset("default").with_overrides(target_mse=None, log2_table=10, time_limit_s=100.0, table_bits=4)
    run = plan_run(s, icosphere(3))
    assert (run.nodes, run.log2_table, run.storage.table_bits) == (s.nodes, 10, 4)
    assert run.training.time_limit_s == 100.0 and run.training.lr == s.lr and run.training.table_bits == 4
    assert (run.metric.views, run.metric.resolution) == (s.eval_views, s.eval_resolution)
    assert run.decision.target_mse is None and run.look.budget_s is None
    assert run.notes[0].kind == "plan" and run.file_bytes > 0
    looked = plan_run(s, crate(cells=2, texture=64))
    assert looked.look.budget_s == pytest.approx(100.0 * s.appearance_share)
    assert looked.training.time_limit_s == pytest.approx(100.0 * (1 - s.appearance_share))
    assert looked.request.time_limit_s == 100.0
    searched = plan_run(s.with_overrides(target_mse=0.001), icosphere(3))  # a target: every size is planned
    bigger = searched.at_table(searched.log2_table + 1)
    assert bigger.log2_table == bigger.request.log2_table == searched.log2_table + 1
    assert bigger.file_bytes > searched.file_bytes
    from nbvh_core.planning.mesh_measures import mesh_features
    from nbvh_core.planning.sizing import LOG2_RANGE, load_fit, predictor
    fit = load_fit()  # the retrain search's predictions are planned too: the size predictor's, at the budget
    if fit is not None:
        predict = predictor(fit, mesh_features(icosphere(3)), None, searched.training.time_limit_s)
        assert set(searched.predicted_log_mse) >= set(LOG2_RANGE)
        assert all(searched.predicted_log_mse[l2] == pytest.approx(predict(l2)) for l2 in LOG2_RANGE)
    assert run.predicted_log_mse == {}
    slower = run.with_training(lr=run.training.lr / 10)
    assert slower.training.lr == slower.request.lr == run.training.lr / 10 and run.training.lr == s.lr


def test_every_default_of_the_request_is_the_default_of_the_part_that_uses_it():
    """One place for every default: a Settings field named as a field of a run's part (training, encoding, network,
    storage, metric, decision, appearance head) defaults to that part's value; every preset names its budget."""
    import dataclasses

    from nbvh_core.decision.config import DecisionConfig
    from nbvh_core.neural.appearance import AppearanceConfig
    from nbvh_core.neural.encodings import EncodingConfig
    from nbvh_core.neural.networks import NetworkConfig
    from nbvh_core.neural.quantize import StorageConfig
    from nbvh_core.planning.settings import PRESETS, Settings
    from nbvh_core.rendering.metrics import MetricConfig
    from nbvh_core.training.train import TrainConfig

    request = {f.name: f.default for f in dataclasses.fields(Settings)}
    renamed = {MetricConfig: {"views": "eval_views", "resolution": "eval_resolution"},
               DecisionConfig: {"check_every_s": "target_check_every_s"},
               AppearanceConfig: {"log2_table": "appearance_log2_table", "target": "appearance_target"}}
    compared = 0
    for part in (TrainConfig, EncodingConfig, NetworkConfig, StorageConfig, MetricConfig, DecisionConfig,
                 AppearanceConfig):
        for f in dataclasses.fields(part):
            name = renamed.get(part, {}).get(f.name, f.name)
            if part is AppearanceConfig and name == f.name or name not in request:
                continue  # the head's own fields (its slots, patches) are the asset's, not the request's
            if (f.default is dataclasses.MISSING or name in ("normal_loss", "normal_weight", "normal_unit_weight")
                    or part is TrainConfig and name in ("table_bits", "network_bits", "rays_per_step")):
                continue  # None: the network's (the device's) own, resolved in planning; TrainConfig's bits: None
                # unless low-bit
            assert request[name] == f.default, f"Settings.{name} = {request[name]!r}, {part.__name__}: {f.default!r}"
            compared += 1
    assert compared >= 30
    for name, s in PRESETS.items():
        assert s.steps is not None or s.time_limit_s is not None, name
