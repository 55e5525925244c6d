"""The napsp method (thesis chapter 6) on the program protocol: settings, rounds, roles, checkpoints.

Everything here runs in-process (LocalRoleGroup) with tiny networks; the
service end to end (Ray, MLflow, faults) is in tests/test_napsp_service.py and
the maze distance figures in tests/test_napsp_maze.py.
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path

import numpy as np
import pytest
import torch
from helpers import cli

from orchestrator.sweep import SweepError, load_sweep
from workers import checkpoint
from workers.distance.config import HASH_SIZES, HER_K
from workers.distance.loop import LoopSettings, NeuralAPSP
from workers.methods import METHODS, LocalRoleGroup, TrialSpec, run_locally
from workers.methods.napsp import NapspProgram, NapspSettings, goal_room_center, state_to_tree, tree_to_state
from workers.tasks import TASKS, make_task

ROOT = Path(__file__).resolve().parents[1]
# The CLI subprocesses (and Ray's workers) import this checkout, not whatever icemlab is installed.
os.environ["PYTHONPATH"] = os.pathsep.join(
    dict.fromkeys([str(ROOT), *filter(None, os.environ.get("PYTHONPATH", "").split(os.pathsep))])
)

TINY = {
    "episodes_per_iteration": 1,
    "eval_episodes": 1,
    "plot_every": 0,
    "learner": {"hidden": [16], "batch_size": 16, "updates_per_episode": 4},
    "distance": {
        "hidden": [16],
        "batch_size": 16,
        "temporal_updates_per_episode": 4,
        "triangular_updates_per_episode": 4,
    },
}


@pytest.fixture(autouse=True)
def one_thread():
    torch.set_num_threads(1)


def trial(task: str = "point_maze", seed: int = 0, **settings) -> TrialSpec:
    """A resolved napsp trial with the tiny settings (overridden by ``settings``)."""
    raw = NapspSettings.model_validate(TINY | {"iterations": 2} | settings)
    return TrialSpec("napsp", task, NapspProgram.resolve(raw, make_task(task, raw.task_options)), seed)


def build(spec: TrialSpec) -> NapspProgram:
    roles = {role.name: LocalRoleGroup.build(role) for role in NapspProgram.roles_for(spec, 1, {})}
    return NapspProgram(spec, roles, 1)


def series_values(reports, key: str) -> list[float]:
    return [value for report in reports for value in report.series.get(key, [])]


# -------------------------------------------------------------- settings
def test_napsp_is_registered_with_the_goal_tasks():
    assert METHODS["napsp"] is NapspProgram
    for name in HASH_SIZES:
        assert name in TASKS and NapspProgram.task_problem(TASKS[name]) is None
    assert "goal task" in NapspProgram.task_problem(TASKS["halfcheetah_running"])
    assert "ground-truth" in METHODS["mpc"].task_problem(TASKS["point_maze"])


@pytest.mark.parametrize("task", sorted(HASH_SIZES))
@pytest.mark.parametrize("reward", ["sparse_her", "ddl_her", "offpolicy_ddl_her", "ours_her"])
def test_unset_settings_resolve_to_the_thesis_tables(task, reward):
    resolved = NapspProgram.resolve(NapspSettings(reward=reward), make_task(task))
    single, pair, sigma = HASH_SIZES[task]
    counts = resolved.counts
    assert (counts.single_key_dim, counts.pair_key_dim, counts.sigma) == (single, pair, sigma)
    assert resolved.learner.her_k == HER_K[task][reward]
    assert resolved.learner.algorithm == ("ddpg" if "pick_place" in task else "sac")
    assert resolved.learner.hidden == (256, 256, 256) and resolved.learner.updates_per_episode == 100
    assert resolved.goal_dim == make_task(task).goal_dim
    horizon = make_task(task).episode_length
    if reward == "sparse_her":
        assert resolved.learner.reward_scale == 1.0 and not resolved.learner.nonnegative_distance
    else:  # -max(d, 0) / T (README: the learned distance's reward)
        assert resolved.learner.reward_scale == 1.0 / horizon and resolved.learner.nonnegative_distance
    if reward == "sparse_her":
        assert resolved.distance.hidden is None  # no distance network
    else:
        assert resolved.distance.learning_rate == 3e-4 and resolved.distance.batch_size == 256
        assert resolved.distance.triangular == (reward == "ours_her")
        assert resolved.distance.conditioning == ("state" if reward == "ddl_her" else "state_action")
        ddl_small = reward == "ddl_her" and task == "point_maze"
        assert resolved.distance.hidden == ((256, 256) if ddl_small else (256, 256, 256))
        assert resolved.distance.buffer_size == (100_000 if reward == "ddl_her" else 1_000_000)


def test_set_fields_override_the_tables_and_resolution_is_idempotent():
    raw = NapspSettings(learner={"her_k": 8, "hidden": [64]}, counts={"sigma": 5.0}, distance={"hidden": [32, 32]})
    resolved = NapspProgram.resolve(raw, make_task("fetch_reach"))
    assert resolved.learner.her_k == 8 and resolved.learner.hidden == (64,)
    assert resolved.counts.sigma == 5.0 and resolved.counts.single_key_dim == 128
    assert resolved.distance.hidden == (32, 32)
    assert NapspProgram.resolve(resolved, make_task("fetch_reach")) == resolved


BAD_INPUT = {
    "hash_size_zero": ("counts: {pair_key_dim: 0}", "base.counts.pair_key_dim", "greater than or equal to 1"),
    "sigma_zero": ("counts: {sigma: 0}", "base.counts.sigma", "greater than 0"),
    "sigma_negative": ("counts: {sigma: -0.3}", "base.counts.sigma", "greater than 0"),
    "her_k_negative": ("learner: {her_k: -1}", "base.learner.her_k", "greater than or equal to 0"),
    "goal_space": ("goal_dim: 3", "goal_dim", "6-D goal space, not 3-D"),
    "ddl_with_triangles": ("reward: ddl_her\n  distance: {triangular: true}", "distance", "triangular: false"),
    "null_hidden": ("distance: {hidden: null}", "distance.hidden", "valid tuple"),
    "triangles_without_counts": (
        "distance: {temporal: regression, triangular: true}",
        "distance",
        "needs temporal: off_policy",
    ),
}


@pytest.mark.parametrize("case", sorted(BAD_INPUT))
def test_bad_input_is_a_located_error_and_nothing_starts(case, tmp_path):
    text, path, fragment = BAD_INPUT[case]
    sweep = tmp_path / f"{case}.yaml"
    sweep.write_text(f"name: bad\ntask: fetch_pick_place\nmethod: napsp\nbase:\n  {text}\nseeds: [0]\n")
    with pytest.raises(SweepError) as error:
        load_sweep(sweep)
    (problem,) = error.value.problems
    assert path in problem.path and fragment in problem.message, problem
    assert problem.line >= 5  # the line of base's entry, not the top of the file


def test_validate_reports_every_problem_with_its_line(tmp_path):
    sweep = tmp_path / "bad.yaml"
    sweep.write_text(
        "name: bad\ntask: point_maze\nmethod: napsp\nbase:\n  counts: {single_key_dim: 0, sigma: 0}\n"
        "  learner: {her_k: -2}\nvariants:\n  - {name: ok}\n  - {name: wrong_goal, goal_dim: 3}\nseeds: [0]\n"
    )
    result = cli("validate", str(sweep), cwd=tmp_path)
    assert result.returncode == 2 and "nothing was started" in result.stderr
    lines = [line for line in result.stderr.splitlines() if line.startswith(str(sweep))]
    assert any(":5: base.counts.single_key_dim:" in line for line in lines)
    assert any(":5: base.counts.sigma:" in line for line in lines)
    assert any(":6: base.learner.her_k:" in line for line in lines)
    wrong = tmp_path / "wrong.yaml"
    wrong.write_text("name: w\ntask: point_maze\nmethod: napsp\nvariants:\n  - {name: g, goal_dim: 3}\nseeds: [0]\n")
    result = cli("validate", str(wrong), cwd=tmp_path)
    assert result.returncode == 2 and ":5: goal_dim: point_maze has a 2-D goal space, not 3-D" in result.stderr


def test_a_method_refuses_the_other_kind_of_task(tmp_path):
    for task, method, fragment in (
        ("halfcheetah_running", "napsp", "needs a goal task"),
        ("point_maze", "mpc", "ground-truth task"),
    ):
        sweep = tmp_path / f"{method}.yaml"
        sweep.write_text(f"name: x\ntask: {task}\nmethod: {method}\nseeds: [0]\n")
        with pytest.raises(SweepError, match=fragment):
            load_sweep(sweep)


# ----------------------------------------------------------------- rounds
def test_method_end_to_end_in_process():
    """Three iterations on Point Maze: every phase's metrics per iteration, versioned weights, figures, summary."""
    spec = trial(iterations=3, plot_every=2)
    reports = run_locally(NapspProgram, spec)
    assert [r.index for r in reports] == [0, 1, 2] and reports[-1].done and not reports[0].done
    assert [r.series_start for r in reports] == [0, 1, 2]  # MLflow step = iteration
    assert series_values(reports, "distance_weights_version") == [1, 2, 3]
    assert series_values(reports, "learner/reward_weights_version") == [1, 2, 3]
    assert series_values(reports, "episodes") == [1, 2, 3]
    assert series_values(reports, "env_steps") == [100, 200, 300]
    for key in (
        "eval/success",
        "eval/max_reward",
        "eval/maze_distance",
        "learner/critic_loss",
        "learner/alpha",
        "learner/q_mean",
        "distance/temporal_loss",
        "distance/triangular_idle_fraction",
        "distance/triangular_merge_rate",
        "distance/triangular_relax_rate",
        "distance/count_mean",
        "counts/pair_increments",
        "time/distance_train",
        "time/learner_train",
        "time/learner_collect",
        "time/learner_evaluate",
    ):
        assert len(series_values(reports, key)) == 3, key
    # The triangular loss is logged for the iterations in which some sample trained (an idle phase has none).
    trained = [idle < 1 for idle in series_values(reports, "distance/triangular_idle_fraction")]
    assert len(series_values(reports, "distance/triangular_loss")) == sum(trained)
    assert series_values(reports, "counts/pair_increments") == [5050, 10100, 15150]  # T (T + 1) / 2 per episode
    # Fig. 22's curves against episodes, rolling means of the evaluation.
    assert [r.step for r in reports] == [1, 2, 3]
    success = series_values(reports, "eval/success")
    assert reports[-1].metrics["rollouts/eval_success"] == pytest.approx(np.mean(success))
    assert [a.path for a in reports[1].artifacts] == [
        "maze/iteration_00002_heatmaps.png",
        "maze/iteration_00002_coverage.png",
    ]
    assert all(a.data.startswith(b"\x89PNG") for r in reports for a in r.artifacts)
    ranks = {k: v for k, v in reports[1].metrics.items() if k.startswith("maze/")}
    assert set(ranks) == {f"maze/{n}_rank_{r}" for n in ("d", "q") for r in ("geodesic", "euclidean")}
    assert all(-1 <= v <= 1 for v in ranks.values()) and not any(k.startswith("maze/") for k in reports[0].metrics)
    summary = reports[-1].summary
    assert summary["total_episodes"] == 3 and summary["eval_success"] == pytest.approx(np.mean(success))
    assert summary["eval_success_episodes"] == 3  # three evaluations of one episode: a rate of 3 episodes
    assert set(NapspProgram.metrics.values()) <= set(summary)


def test_maze_rank_metrics_tell_a_wall_aware_distance_from_the_straight_line():
    from workers.methods.napsp import MazeViews, goal_room_center
    from workers.tasks.goal_tasks import PointMaze

    maze = PointMaze()
    field = maze.maze_distance
    goal = goal_room_center(maze.maze_map)
    centers = field.cell_centers()
    geodesic = field.distance_field(goal)
    euclidean = np.linalg.norm(centers - goal, axis=-1)

    def views(d):
        return MazeViews(goal, field.free, geodesic, euclidean, d, 2 * d)

    aware = views(3 * geodesic + 1).rank_metrics()
    assert aware["maze/d_rank_geodesic"] == pytest.approx(1.0) and aware["maze/q_rank_geodesic"] == pytest.approx(1.0)
    assert aware["maze/d_rank_euclidean"] < 0.7  # behind the walls the two orders differ
    blind = views(euclidean).rank_metrics()
    assert blind["maze/d_rank_euclidean"] == pytest.approx(1.0) and blind["maze/d_rank_geodesic"] < 0.7
    sparse = MazeViews(goal, field.free, geodesic, euclidean, None, euclidean).rank_metrics()
    assert set(sparse) == {"maze/q_rank_geodesic", "maze/q_rank_euclidean"}


def test_sparse_her_has_no_distance_role():
    spec = trial(reward="sparse_her")
    assert [role.name for role in NapspProgram.roles_for(spec, 1, {})] == ["learner"]
    reports = run_locally(NapspProgram, spec)
    assert not series_values(reports, "distance_weights_version")
    assert len(series_values(reports, "learner/critic_loss")) == 2


@pytest.mark.parametrize("reward", ["sparse_her", "ddl_her", "ours_her"])
def test_sync_mode_is_the_in_process_loop(reward):
    """The service's split into roles changes nothing: sync napsp equals NeuralAPSP iteration for iteration."""
    spec = trial("fetch_reach", seed=3, reward=reward, iterations=3)
    reports = run_locally(NapspProgram, spec)
    settings = spec.settings
    overrides = {
        "counts": settings.counts.model_dump(),
        "learner": settings.learner.model_dump(),
        "distance": settings.distance.model_dump() if reward != "sparse_her" else {},
    }
    loop_settings = LoopSettings(
        method=reward, task="fetch_reach", seed=3, episodes_per_iteration=1, eval_episodes=1, **overrides
    )
    loop = NeuralAPSP(loop_settings)
    history = loop.run(3)
    loop.close()
    for key in ("eval/final_goal_distance", "collect/final_goal_distance", "learner/critic_loss"):
        assert series_values(reports, key) == [m[key] for m in history], key
    if reward != "sparse_her":
        assert series_values(reports, "distance/temporal_loss") == [m["distance/temporal_loss"] for m in history]


def test_pipelined_mode_trains_the_policy_on_the_previous_distance():
    reports = run_locally(NapspProgram, trial(mode="pipelined", iterations=3))
    assert series_values(reports, "distance_weights_version") == [1, 1, 2]  # what the learner trained on
    assert series_values(reports, "learner/reward_weights_version") == [1, 1, 2]
    assert NapspProgram.label_text(NapspProgram.labels(trial(mode="pipelined"))) == ["ours_her", "pipelined"]


def test_roles_hold_one_unit_in_sync_and_two_when_pipelined():
    for mode, total in (("sync", 2.0), ("pipelined", 3.5)):
        spec = trial(mode=mode)
        roles = NapspProgram.roles_for(spec, 2, {})
        assert {role.name: role.stateful for role in roles} == {"learner": True, "distance": True}
        assert NapspProgram.runner_cpus(spec, 2) + sum(role.cpus for role in roles) == total
        assert all(role.kwargs["threads"] == 2 for role in roles)


def test_mode_comparison_runs_both_modes_alike_and_skips_the_warmup():
    from workers.distance.bench import compare_modes

    programs = {mode: build(trial(mode=mode, iterations=3)) for mode in ("sync", "pipelined")}
    figures = compare_modes(programs, iterations=2, warmup=1)
    assert all(program.iteration == 3 for program in programs.values())
    seconds = figures["seconds_per_iteration"]
    assert set(seconds) == {"sync", "pipelined"} and figures["iterations"] == 2
    assert figures["pipelined_over_sync"] == pytest.approx(seconds["pipelined"] / seconds["sync"])


def test_iterations_per_round_change_nothing_but_the_rounds():
    one = run_locally(NapspProgram, trial(iterations=3))
    blocks = run_locally(NapspProgram, trial(iterations=3, iterations_per_round=2))
    assert [len(r.series["eval/success"]) for r in blocks] == [2, 1] and [r.series_start for r in blocks] == [0, 2]
    assert series_values(one, "eval/max_reward") == series_values(blocks, "eval/max_reward")
    assert NapspProgram.planned_rounds(trial(iterations=3, iterations_per_round=2)) == 2


# ------------------------------------------------------------- checkpoints
@pytest.mark.parametrize("mode", ["sync", "pipelined"])
def test_checkpoint_round_trip_continues_identically(mode):
    """Rounds 0-1, a checkpoint through the on-disk format, fresh roles, rounds 2-3 = an uninterrupted run."""
    spec = trial(mode=mode, iterations=4)
    uninterrupted = run_locally(NapspProgram, spec)

    first = build(spec)
    for index in range(2):
        first.run_round(index)
    data = checkpoint.to_bytes({"program": first.state_dict()})
    first.close()
    second = build(spec)  # new learner and DistanceTrainer, as after a lost process
    second.load_state_dict(checkpoint.from_bytes(data)["program"])
    resumed = [second.run_round(index) for index in (2, 3)]
    second.close()
    for key in ("eval/max_reward", "learner/critic_loss", "distance/temporal_loss", "distance/triangular_loss"):
        # Bit for bit; nan (a triangular phase that trained nothing) equals nan here.
        np.testing.assert_array_equal(series_values(resumed, key), series_values(uninterrupted[2:], key), key)
    versions = "distance_weights_version"
    assert series_values(resumed, versions) == series_values(uninterrupted[2:], versions)
    assert resumed[-1].summary == pytest.approx(uninterrupted[-1].summary, nan_ok=True)


def test_distance_trainer_state_holds_weights_sketches_and_buffer():
    program = build(trial())
    program.run_round(0)
    state = program.distance.submit(0, "state").result()
    keys = set(state.arrays)
    assert {"model/function/net/0.weight", "model/target/net/0.weight", "model/target/obs_norm/total"} <= keys
    assert any(key.startswith("counts/single/sketch/") for key in keys)
    assert any(key.startswith("counts/pair/sketch/") for key in keys)
    assert state.arrays["buffer/observations"].shape == (1, 101, 4)
    assert state.meta["version"] == 1
    assert tree_to_state(state_to_tree(state)).meta == json.loads(json.dumps(state.meta))
    restored = tree_to_state(checkpoint.from_bytes(checkpoint.to_bytes({"s": state_to_tree(state)}))["s"])
    assert set(restored.arrays) == keys
    assert all(np.array_equal(restored.arrays[k], state.arrays[k]) for k in keys)
    program.close()


def test_goal_room_center_is_the_middle_of_the_goal_cells():
    from workers.tasks.goal_tasks import FOUR_ROOMS

    assert goal_room_center(FOUR_ROOMS) == pytest.approx([1.5, 1.5])
    assert math.isclose(make_task("point_maze").maze_distance.distance(np.array([[1.5, 1.5]]), [1.5, 1.5])[0], 0.0)
