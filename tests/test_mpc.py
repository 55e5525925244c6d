"""The MPC loop, the MPC program and the runner, in-process (no Ray)."""

from __future__ import annotations

import numpy as np
import pytest

from workers import checkpoint, code_fingerprint
from workers.actors import CheckpointMismatchError, ProgramRunner
from workers.methods import METHODS, LocalRoleGroup, MpcSettings, TrialSpec, run_locally
from workers.methods.mpc import episode_seed
from workers.mpc import MpcEpisode, run_episode
from workers.planning import CEMPlanner, PlannerConfig
from workers.simulation import SimulationPool, SimulationWorker
from workers.tasks import make_task


def trial(task_name: str = "point_reach", seed: int = 3, **overrides) -> TrialSpec:
    settings = dict(planner=dict(budget=50, horizon=10), max_steps=12) | overrides
    resolved = METHODS["mpc"].resolve(MpcSettings(**settings), make_task(task_name))
    return TrialSpec("mpc", task_name, resolved, seed)


def rewards(reports) -> list[float]:
    return [r for report in reports for r in report.series["step/reward"]]


def test_episode_report_is_consistent():
    (report,) = run_locally(METHODS["mpc"], trial())
    assert report.done and len(report.series["step/reward"]) == 12
    assert report.metrics["episode_return"] == pytest.approx(sum(report.series["step/reward"]))
    assert "success" not in report.metrics  # the tiny task has no success criterion
    assert report.metrics["simulated_steps_per_second"] > 0
    # iCEM at budget 50: 25 + 20 trajectories, plus 3 shifted elites from the second step on
    trajectories = report.series["step/trajectories"]
    assert trajectories[0] == 45 and set(trajectories[1:]) == {48}
    assert report.summary["mean_return"] == pytest.approx(report.metrics["episode_return"])
    assert {a.path for a in report.artifacts} == {"episodes/episode_000.png", "episodes/episode_000.npz"}


def test_rounds_split_episodes_into_segments_with_steps_counted_across_episodes():
    reports = run_locally(METHODS["mpc"], trial(max_steps=10, round_steps=4, episodes=2))
    assert [len(r.series["step/reward"]) for r in reports] == [4, 4, 2, 4, 4, 2]
    assert [r.series_start for r in reports] == [0, 4, 8, 10, 14, 18]
    assert [bool(r.metrics) for r in reports] == [False, False, True, False, False, True]
    assert [r.step for r in reports if r.metrics] == [0, 1]
    assert [r.done for r in reports] == [False] * 5 + [True]


def test_same_seed_same_episode_and_episodes_differ():
    first = run_locally(METHODS["mpc"], trial(seed=5, episodes=2, max_steps=10))
    again = run_locally(METHODS["mpc"], trial(seed=5, episodes=2, max_steps=10))
    assert rewards(first) == rewards(again)
    assert episode_seed(5, 0) == 5 and episode_seed(5, 1) != 5
    assert first[0].metrics["episode_return"] != first[1].metrics["episode_return"]


@pytest.mark.parametrize(
    "task_name",
    ["point_reach", "halfcheetah_running", pytest.param("fetch_pick_place_sparse", marks=pytest.mark.slow)],
)
def test_restored_checkpoint_continues_bit_for_bit(task_name):
    """A runner that restores a mid-episode checkpoint produces exactly the uninterrupted trial."""
    spec = trial(task_name, seed=1, max_steps=9, round_steps=4, episodes=2)
    uninterrupted = ProgramRunner(spec, {}, 1)
    total = uninterrupted.total_rounds()
    expected = [uninterrupted.run_round(i)[0] for i in range(total)]
    first = ProgramRunner(spec, {}, 1)
    before = [first.run_round(i)[:2] for i in range(4)]  # mid-way through the second episode
    resumed = ProgramRunner(spec, {}, 1)
    assert resumed.restore(before[-1][1]) == 4
    after = [resumed.run_round(i)[0] for i in range(4, total)]
    assert rewards([r for r, _ in before] + after) == rewards(expected)
    assert after[-1].summary["mean_return"] == expected[-1].summary["mean_return"]


def test_runner_refuses_rounds_out_of_order_and_foreign_checkpoints():
    runner = ProgramRunner(trial(), {}, 1)
    with pytest.raises(RuntimeError, match="round 1"):
        runner.run_round(1)
    _, data, _ = runner.run_round(0)
    other = ProgramRunner(trial(seed=4), {}, 1)
    with pytest.raises(CheckpointMismatchError):
        other.restore(data)
    with pytest.raises(checkpoint.CheckpointError):
        other.restore(b"not a checkpoint")


def test_a_checkpoint_other_code_wrote_and_this_code_cannot_load_says_so():
    """A program state this code cannot read: from other code, the error names both fingerprints and what to do
    (a code error, not retried into an earlier checkpoint); from this code, the program's own error stands."""
    from orchestrator.failures import CODE_ERROR, classify
    from workers.actors import CheckpointFromOtherCodeError

    _, data, _ = ProgramRunner(trial(), {}, 1).run_round(0)
    tree = checkpoint.from_bytes(data)
    tree["program"] = {}  # what a program whose state keys were renamed since would find
    with pytest.raises(KeyError):
        ProgramRunner(trial(), {}, 1).restore(checkpoint.to_bytes(tree))
    tree["code"] = "0123456789abcdef"
    with pytest.raises(CheckpointFromOtherCodeError, match="0123456789abcdef") as error:
        ProgramRunner(trial(), {}, 1).restore(checkpoint.to_bytes(tree))
    failure = classify(error.value)
    assert failure.kind == CODE_ERROR and "resume with the icemlab that wrote it" in failure.cause


def test_planning_beats_doing_nothing():
    """iCEM drives the point mass to its goal: far better than zero actions from the same start."""
    task = make_task("point_reach")
    env = task.make_env()
    env.reset(seed=2)
    idle = sum(task.step_env(env, np.zeros(task.action_dim)).reward for _ in range(30))
    (report,) = run_locally(METHODS["mpc"], trial(seed=2, max_steps=30, round_steps=30))
    assert report.metrics["episode_return"] > idle + 1.0


def test_pool_splits_batches_over_workers_without_changing_costs():
    """A co-located worker plus two in-process 'remote' ones give the costs of a single worker."""
    task = make_task("halfcheetah_running")
    remote = LocalRoleGroup("simulation", [SimulationWorker("halfcheetah_running") for _ in range(2)])
    pooled, single = SimulationPool(task.name, 1, remote), SimulationPool(task.name, 1)
    env = task.make_env()
    env.reset(seed=0)
    from workers.mpc import PlanningState

    state = PlanningState(np.zeros(17), task.capture(env))
    actions = np.random.default_rng(0).uniform(-1, 1, (25, 5, task.action_dim))
    np.testing.assert_array_equal(pooled.evaluate(state, actions), single.evaluate(state, actions))


def test_pool_notices_a_worker_restarted_after_its_last_evaluation():
    """A worker replaced between evaluations counts once, whether the next evaluation or the end-of-episode
    check sees it first."""
    task = make_task("point_reach")
    remote = LocalRoleGroup("simulation", [SimulationWorker(task.name) for _ in range(2)])
    pool = SimulationPool(task.name, None, remote)
    env = task.make_env()
    from workers.mpc import PlanningState

    observation, _ = env.reset(seed=0)
    state = PlanningState(observation, task.capture(env))
    actions = np.zeros((4, 3, task.action_dim))
    pool.evaluate(state, actions)
    assert pool.check_restarts() == 0
    remote.workers[1] = SimulationWorker(task.name)  # the service restarted it: a new process, a new incarnation
    assert pool.check_restarts() == 1
    pool.evaluate(state, actions)
    assert pool.check_restarts() == 1


def test_success_tasks_count_goal_steps():
    """goal_steps is the number of steps on which the environment reported its goal condition."""
    task = make_task("fetch_pick_place_sparse")
    env = task.make_env()
    config = PlannerConfig(budget=50, horizon=5).resolved(task.colored_noise_beta)
    pool = SimulationPool(task.name, 1)
    episode = MpcEpisode(task, env, CEMPlanner(config, task.action_dim, seed=0), pool, seed=0, steps=4)
    flags = []
    episode.run(on_step=lambda record: flags.append(record.goal_achieved))
    result = episode.result()
    assert result.goal_steps == sum(flags) and result.success == flags[-1]
    # Place the box on its target: every later step is a goal step and the episode succeeds.
    env.unwrapped._utils.set_joint_qpos(env.unwrapped.model, env.unwrapped.data, "object0:joint",
                                        np.concatenate([env.unwrapped.goal, [1, 0, 0, 0]]))  # fmt: skip
    env.unwrapped.data.qvel[:] = 0
    import mujoco

    mujoco.mj_forward(env.unwrapped.model, env.unwrapped.data)
    episode.steps = 6
    episode.run()
    result = episode.result()
    assert result.goal_steps == sum(flags) + 2 and result.success


def test_run_episode_matches_the_program():
    spec = trial(seed=7)
    task = make_task(spec.task)
    env = task.make_env()
    planner = CEMPlanner(spec.settings.planner, task.action_dim, seed=7)
    result = run_episode(task, env, planner, SimulationPool(task.name, 1), seed=7, steps=12)
    (report,) = run_locally(METHODS["mpc"], spec)
    assert list(result.rewards) == list(report.series["step/reward"])


def test_planner_seed_offset_replays_the_same_start_with_other_samples():
    """The offset reseeds the planner's noise only: the trial is the episode reset with its own seed and
    planned with seed + offset, and its actions differ from the default's."""
    spec = trial(seed=5, planner_seed_offset=1000)
    task = make_task(spec.task)
    planner = CEMPlanner(spec.settings.planner, task.action_dim, seed=5)
    episode = MpcEpisode(task, task.make_env(), planner, SimulationPool(task.name, 1), 5, 12, planner_seed=1005)
    episode.run()
    (replay,) = run_locally(METHODS["mpc"], spec)
    (plain,) = run_locally(METHODS["mpc"], trial(seed=5))
    assert list(episode.result().rewards) == rewards([replay])
    assert rewards([replay]) != rewards([plain])


def test_runner_refuses_code_that_differs_from_the_driver():
    with pytest.raises(RuntimeError, match="different icemlab code"):
        ProgramRunner(trial(), {}, 1, expected_code="0" * 16)
    ProgramRunner(trial(), {}, 1, expected_code=code_fingerprint())


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
