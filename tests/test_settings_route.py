"""One route from a request to Settings, shared by the command line, the add-on's job and library batches."""
import pytest

from nbvh_core.planning.settings import preset, settings_from_request


def test_a_request_is_its_preset_with_the_fields_it_names():
    s = settings_from_request({"preset": "preview", "log2_table": 9, "seed": None})
    assert s.log2_table == 9 and s.nodes == preset("preview").nodes and s.seed == preset("preview").seed
    assert settings_from_request({}) == preset("default")


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
    for name in ("cli.py", "job.py", "library_batch.py"):
        calls = {n.func.id if isinstance(n.func, ast.Name) else getattr(n.func, "attr", "")
                 for n in ast.walk(ast.parse((app / name).read_text())) if isinstance(n, ast.Call)}
        assert "settings_from_request" in calls, name
