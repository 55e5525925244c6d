"""The MPC loop and the actor shells, in-process (no Ray)."""

from __future__ import annotations

import numpy as np
import pytest

from orchestrator.pool import SimulationPool
from workers import code_fingerprint
from workers.actors import TrialRunner, episode_seed
from workers.planning import PlannerConfig
from workers.tasks import make_task


def config(task_name: str, **overrides) -> PlannerConfig:
    settings = dict(budget=50, horizon=10) | overrides
    return PlannerConfig(**settings).resolved(make_task(task_name).colored_noise_beta)


def test_episode_report_is_consistent():
    runner = TrialRunner("point_reach", config("point_reach"), seed=3, max_steps=12)
    report = runner.run_episode(0).result
    assert len(report.rewards) == len(report.planning_seconds) == len(report.trajectories) == 12
    assert report.episode_return == pytest.approx(report.rewards.sum())
    assert report.success is None and report.goal_steps is None  # the tiny task has no success criterion
    assert np.all(report.planning_seconds > 0) and report.simulated_steps_per_second > 0
    # iCEM at budget 50: 25 + 20 trajectories, plus 3 shifted elites from the second step on
    assert report.trajectories[0] == 45 and set(report.trajectories[1:]) == {48}
    assert runner.progress() == {"episode": 0, "step": 12, "steps": 12}


def test_same_seed_same_episode_and_episodes_differ():
    runner = TrialRunner("point_reach", config("point_reach"), seed=5, max_steps=10)
    first, again, second = runner.run_episode(0), runner.run_episode(0), runner.run_episode(1)
    np.testing.assert_array_equal(first.result.rewards, again.result.rewards)
    assert second.seed == episode_seed(5, 1) != first.seed == 5
    assert not np.array_equal(first.result.rewards, second.result.rewards)


def test_planning_beats_doing_nothing():
    """iCEM drives the point mass to its goal: far better than zero actions from the same start."""
    task = make_task("point_reach")
    env = task.make_env()
    env.reset(seed=2)
    idle = sum(task.step_env(env, np.zeros(task.action_dim)).reward for _ in range(30))
    planned = TrialRunner("point_reach", config("point_reach"), seed=2, max_steps=30).run_episode(0).result
    assert planned.episode_return > idle + 1.0


def test_pool_with_a_co_located_worker_needs_no_ray():
    """The default SimulationPool layout evaluates in-process and gives the same episode."""
    planner = config("point_reach")
    pooled = TrialRunner("point_reach", planner, 4, SimulationPool("point_reach", 1, []), max_steps=8).run_episode(0)
    direct = TrialRunner("point_reach", planner, 4, max_steps=8).run_episode(0)
    np.testing.assert_array_equal(pooled.result.rewards, direct.result.rewards)


def test_success_tasks_count_goal_steps():
    runner = TrialRunner("fetch_pick_place_sparse", config("fetch_pick_place_sparse"), seed=0, max_steps=2)
    report = runner.run_episode(0).result
    assert report.success in (True, False) and report.goal_steps in (0, 1, 2)


def test_runner_refuses_code_that_differs_from_the_driver():
    with pytest.raises(RuntimeError, match="different icemlab code"):
        TrialRunner("point_reach", config("point_reach"), seed=0, expected_code="0" * 16)
    TrialRunner("point_reach", config("point_reach"), seed=0, expected_code=code_fingerprint(), max_steps=1)


@pytest.mark.parametrize(
    "shape, fill, message",
    [
        ((4, 5), 0.0, "must be"),
        ((4, 5, 3), 0.0, r"\(N, horizon, 2\)"),
        ((0, 5, 2), 0.0, "must be"),
        ((2, 3, 2), np.nan, "NaN"),
    ],
)
def test_evaluator_rejects_bad_batches_before_mujoco(shape, fill, message, task_bundle):
    from workers.rollout import BatchEvaluator

    task, env, model = task_bundle("point_reach")
    state = task.capture(env)
    with BatchEvaluator(task, model, threads=1) as evaluator, pytest.raises(ValueError, match=message):
        evaluator.costs(state, np.full(shape, fill))
