"""The run's wall (`app.run_wall`): the training fitted to 1.25x the run's budget from the run's start."""
import dataclasses

import pytest

from nbvh_core.app.run_wall import END_RESERVE, MIN_TRAINING_SHARE, RUN_WALL_FACTOR, within_wall
from nbvh_core.planning.run_config import plan_run
from nbvh_core.planning.settings import preset


@pytest.fixture(scope="module")
def default_run(sample_meshes):
    return plan_run(preset("default").with_overrides(time_limit_s=200.0, target_mse=0.0005), sample_meshes["blob"])


def test_a_light_run_keeps_its_budget_and_the_margin_goes_to_its_checks(default_run):
    run, note = within_wall(default_run, started_at=0.0, now=12.0)
    assert note is None and run.training.time_limit_s == 200.0
    assert run.training.checks_outside_budget_s == pytest.approx(RUN_WALL_FACTOR * 200 - 12 - 200 - END_RESERVE * 200)


def test_a_run_whose_plan_ate_the_margin_trains_shorter_and_says_so(default_run):
    run, note = within_wall(default_run, started_at=0.0, now=60.0)
    assert run.training.time_limit_s == pytest.approx(RUN_WALL_FACTOR * 200 - 60 - END_RESERVE * 200)
    assert run.training.checks_outside_budget_s == 0.0
    assert note.kind == "wall" and "188 s of its 200 s" in note.text
    assert default_run.training.time_limit_s == 200.0  # the planned run is not changed


def test_a_training_is_never_cut_below_its_floor(default_run):
    run, note = within_wall(default_run, started_at=0.0, now=500.0)
    assert run.training.time_limit_s == MIN_TRAINING_SHARE * 200 and note is not None


def test_the_look_s_share_is_kept_out_of_the_geometry_s_wall(default_run):
    with_look = dataclasses.replace(default_run, training=dataclasses.replace(default_run.training, time_limit_s=160.0),
                                    look=dataclasses.replace(default_run.look, budget_s=40.0))
    run, note = within_wall(with_look, started_at=0.0, now=12.0)
    assert note is None and run.training.time_limit_s == 160.0
    assert run.training.checks_outside_budget_s == pytest.approx(RUN_WALL_FACTOR * 200 - 12 - 40 - 160 - END_RESERVE * 200)


def test_a_run_in_steps_has_no_wall(sample_meshes):
    steps_run = plan_run(preset("tiny"), sample_meshes["blob"])
    assert within_wall(steps_run, started_at=0.0, now=1e6) == (steps_run, None)
