"""The mbrl method (thesis chapter 5): settings, the loop in-process, checkpoints, roles, bad input, reports.

In-process tests use tiny settings (a 16-unit ensemble, 10-step episodes,
a dozen sequences per CEM-iteration); the service tests (real Ray, real
MLflow, real faults) and the smoke sweep through the CLI are marked slow.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml
from helpers import cli
from pydantic import ValidationError

from workers import checkpoint
from workers.dynamics.ensemble import DynamicsEnsemble
from workers.methods import METHODS, TrialSpec
from workers.methods.base import LocalRoleGroup
from workers.methods.mbrl import TABLE_15, MbrlProgram, MbrlSettings, episode_ending, frozen_rows
from workers.planning.config import PlannerConfig
from workers.tasks import make_task

ROOT = Path(__file__).resolve().parents[1]

TINY: dict[str, Any] = {
    "task_options": {"episode_length": 10},
    "model": {"preset": "small", "hidden_size": 16, "hidden_layers": 2, "epochs": 2, "batch_size": 16},
    "planner": {"population": 12, "iterations": 2, "horizon": 4, "elites": 4},
    "razer": {"epistemic_weight": 0.05},
    "random_episodes": 2,
    "iterations": 2,
    "model_every": 1,
    "frozen": {"episodes": 3, "pets": True, "aleatoric_weights": [0.5]},
}


def tiny_trial(seed: int = 0, task: str = "bridge_maze", **changes: Any) -> TrialSpec:
    raw = {**TINY, **changes}
    settings = MbrlSettings.model_validate(raw)
    resolved = MbrlProgram.resolve(settings, make_task(task, settings.task_options))
    return TrialSpec("mbrl", task, resolved, seed)


class RecordingGroup(LocalRoleGroup):
    """In-process role workers that remember what they were asked."""

    def __init__(self, name, workers):
        super().__init__(name, workers)
        self.calls: list[tuple[int, str, tuple]] = []
        self.shared: list[Any] = []

    def submit(self, member, method, *args):
        self.calls.append((member, method, args))
        return super().submit(member, method, *args)

    def share(self, value):
        self.shared.append(value)
        return value


def build(trial: TrialSpec, planners: int = 1) -> MbrlProgram:
    specs = MbrlProgram.roles_for(trial, 1, {"planner": planners})
    roles = {
        spec.name: RecordingGroup(spec.name, [spec.worker(**spec.kwargs) for _ in range(spec.count)]) for spec in specs
    }
    return MbrlProgram(trial, roles, 1)


def run_rounds(program: MbrlProgram, rounds) -> list:
    return [program.run_round(index) for index in rounds]


# ------------------------------------------------------------------ settings
def test_a_planner_budget_or_algorithm_of_the_sweep_is_not_overridden_by_table_15():
    """Table 15 fixes iCEM's iterations, population and switches; a sweep's budget must choose the schedule
    instead (not be overwritten by 393), and another algorithm must run with its own preset, not Table 15's."""
    bridge = make_task("bridge_maze")
    budget = MbrlProgram.resolve(MbrlSettings(planner={"budget": 60}), bridge).planner
    assert budget.budget == 60 and (budget.iterations, budget.population) != (3, 128)
    spent = PlannerConfig(**budget.model_dump()).trajectories_per_step()
    assert abs(spent - 60) <= 5  # a schedule close to the budget, plus the re-evaluated elites
    pets = MbrlProgram.resolve(MbrlSettings(planner={"algorithm": "cem_pets"}), bridge).planner
    assert (pets.bounds, pets.keep_elites, pets.shift_elites, pets.best_action, pets.add_mean, pets.noise_beta) == (
        "truncate_2sigma", False, False, False, False, 0.0)
    assert (pets.iterations, pets.population, pets.horizon) == (3, 128, 30)  # what is not a switch stays Table 15's
    iterations = MbrlProgram.resolve(MbrlSettings(planner={"iterations": 2}), bridge).planner
    assert (iterations.iterations, iterations.population) == (2, 128) and iterations.budget == 2 * 128 + 3 + 3


def test_resolution_fills_the_thesis_tables_per_task():
    bridge = MbrlProgram.resolve(MbrlSettings(), make_task("bridge_maze"))
    assert bridge.model.preset == "bridge_maze" and (bridge.model.hidden_layers, bridge.model.hidden_size) == (6, 400)
    planner = bridge.planner
    for key, value in TABLE_15.items():
        if key != "budget":
            assert getattr(planner, key) == value, key
    assert planner.noise_beta == 2.0 and planner.budget == 3 * 128 + 3 + 2 * 3  # + shifted + re-evaluated elites
    cheetah = MbrlProgram.resolve(MbrlSettings(), make_task("noisy_halfcheetah"))
    assert (cheetah.planner.population, cheetah.planner.iterations, cheetah.planner.noise_beta) == (120, 4, 0.25)
    assert cheetah.model.preset == "noisy_halfcheetah" and cheetah.model.min_logvar == -6.0
    # The task's own safety box (the ceiling) is filled in; explicit settings win over the tables.
    assert [box.dims for box in cheetah.razer.safety_boxes] == [(0,)]
    custom = MbrlProgram.resolve(MbrlSettings(planner={"horizon": 12}, model={"epochs": 3}), make_task("bridge_maze"))
    assert custom.planner.horizon == 12 and custom.planner.population == 128 and custom.model.epochs == 3


def test_the_cost_label_names_every_term_of_razers_cost():
    """A run with the safety term (eq. 35) is neither PETS nor the plain w_A / w_E configuration."""
    task = make_task("noisy_halfcheetah")

    def label(**razer) -> str:
        settings = MbrlProgram.resolve(MbrlSettings(razer=razer), task)
        return MbrlProgram.labels(TrialSpec("mbrl", task.name, settings, 0))["cost"]

    assert label(mean_propagation="none") == "pets"
    assert label(mean_propagation="none", safety_weight=1.0) == "razer_wA0_wE0_wS1_delta0.05"
    assert label(aleatoric_weight=0.05, safety_weight=1.0, safety_delta=0.1) == "razer_wA0.05_wE0_wS1_delta0.1"
    assert label(aleatoric_weight=0.05) == "razer_wA0.05_wE0"
    assert label(aleatoric_weight=0.05, aleatoric_states="means") == "razer_wA0.05_wE0_Ameans"


def test_frozen_rows_read_the_aleatoric_variance_where_each_set_of_rows_says():
    settings = MbrlSettings(
        razer={"epistemic_weight": 0.05},
        frozen={"episodes": 5, "aleatoric_weights": [0.25, 0.5], "aleatoric_states": ["particles", "means"]},
    )
    rows = frozen_rows(settings)
    assert [name for name, _ in rows] == [
        "pets", "razer_wA_0.25", "razer_wA_0.5", "razer_wA_0.25_means", "razer_wA_0.5_means"
    ]  # fmt: skip
    assert [r.aleatoric_states for _, r in rows] == ["particles"] * 3 + ["means"] * 2
    assert all(r.settings(()).propagated_means() == "per_member" for _, r in rows[3:])
    assert rows[1][1].settings(()).propagated_means() == "none"  # w_E 0 and Var_A at the particles: no means
    for states, problem in (([], "at least one"), (["means", "means"], "repeat")):
        with pytest.raises(ValidationError, match=problem):
            MbrlSettings(frozen={"episodes": 5, "aleatoric_weights": [0.25], "aleatoric_states": states})
    with pytest.raises(ValidationError, match="needs mean_propagation"):
        MbrlSettings(razer={"aleatoric_states": "means", "mean_propagation": "none"})


def test_the_best_frozen_row_is_picked_within_each_reading_of_var_a():
    from workers.methods.mbrl import best_frozen_success

    frozen = {"episodes": 5, "aleatoric_weights": [0.25, 0.5]}
    both = frozen_rows(MbrlSettings(frozen=frozen | {"aleatoric_states": ["particles", "means"]}))
    rates = {"pets": 0.9, "razer_wA_0.25": 0.2, "razer_wA_0.5": 0.4, "razer_wA_0.25_means": 0.8,
             "razer_wA_0.5_means": 0.6}  # fmt: skip
    results = {row: {"success_rate": rate} for row, rate in rates.items()}
    assert best_frozen_success(results, both) == {
        "frozen_best_success_rate": 0.4, "frozen_best_success_rate_means": 0.8
    }  # fmt: skip
    means_only = frozen_rows(MbrlSettings(frozen=frozen | {"aleatoric_states": ["means"]}))
    assert best_frozen_success(results, means_only) == {"frozen_best_success_rate": 0.8}
    assert best_frozen_success({"pets": {"success_rate": 0.9}}, both) == {}


def test_frozen_rows_are_pets_then_razer_by_weight():
    settings = MbrlSettings(
        razer={"epistemic_weight": 0.05, "safety_weight": 0.0}, frozen={"episodes": 5, "aleatoric_weights": [0.1, 1.0]}
    )
    rows = frozen_rows(settings)
    assert [name for name, _ in rows] == ["pets", "razer_wA_0.1", "razer_wA_1"]
    pets = rows[0][1]
    assert pets.is_pets() and pets.mean_propagation == "none"
    assert [(r.aleatoric_weight, r.epistemic_weight, r.mean_propagation) for _, r in rows[1:]] == [
        (0.1, 0.0, "per_member"),
        (1.0, 0.0, "per_member"),
    ]
    assert MbrlProgram.planned_rounds(TrialSpec("mbrl", "bridge_maze", settings, 0)) == 1 + 10 + 3


@pytest.mark.parametrize("planners, row", [(1, 5.0), (2, 3.0), (5, 1.0)])
def test_a_frozen_row_weighs_its_episodes_spread_over_the_planning_workers(planners, row):
    """Times to go weigh rounds by this: a frozen row of 5 episodes takes as long as ceil(5 / workers) iterations."""
    settings = MbrlSettings(iterations=10, frozen={"episodes": 5, "aleatoric_weights": [0.1, 1.0]})
    spec = TrialSpec("mbrl", "bridge_maze", settings, 0)
    work = MbrlProgram.round_work(spec, {"planner": planners})
    assert len(work) == MbrlProgram.planned_rounds(spec)
    assert work == [0.0] + [1.0] * 10 + [row] * 3
    # Frozen episodes twice as long as the loop's weigh twice as much.
    longer = MbrlSettings(
        iterations=10,
        task_options={"episode_length": 100},
        frozen={"episodes": 5, "aleatoric_weights": [0.1, 1.0], "task_options": {"episode_length": 200}},
    )
    work = MbrlProgram.round_work(TrialSpec("mbrl", "bridge_maze", longer, 0), {"planner": planners})
    assert work == [0.0] + [1.0] * 10 + [2 * row] * 3


# --------------------------------------------------------------- the loop
@pytest.fixture(scope="module")
def tiny_run():
    """The whole tiny trial with three planning workers (the runner's and two actors), round by round."""
    trial = tiny_trial()
    program = build(trial, planners=3)
    reports = run_rounds(program, range(program.total_rounds()))
    yield trial, program, reports
    program.close()


def test_the_loop_collects_trains_and_evaluates(tiny_run):
    trial, program, reports = tiny_run
    assert len(reports) == MbrlProgram.planned_rounds(trial) == 1 + 2 + 2
    assert [r.step for r in reports] == [0, 1, 2, 0, 1] and [r.done for r in reports] == [False] * 4 + [True]
    zero, first, second = (r.metrics for r in reports[:3])
    # Round 0: two colored-noise episodes of 10 steps, one training call; nothing to hold out yet.
    assert zero["dataset_size"] == 20 and zero["weights_version"] == 1 and "held_out_nll" not in zero
    # Iterations: one planned episode each on the previous weights, held out before training on it.
    for index, metrics in ((1, first), (2, second)):
        assert metrics["planned_with_version"] == index and metrics["weights_version"] == index + 1
        assert metrics["dataset_size"] == 20 + 10 * index
        for key in (
            "train_nll",
            "train_mse",
            "held_out_nll",
            "held_out_mse",
            "logvar_at_bound",
            "train_seconds",
            "episode_return",
            "success",
            "falls",
            "coverage",
            "cost/c",
            "cost/c_A",
            "cost/c_E",
            "cost/c_S",
        ):
            assert math.isfinite(metrics[key]), key
        assert metrics["cost/c_E"] < 0 < metrics["cost/u_E"]  # w_E = 0.05: a bonus
        assert metrics["cost/c_A"] == 0.0  # w_A = 0 during training
    assert zero["coverage"] <= first["coverage"] <= second["coverage"]  # cumulative over the dataset
    # Frozen rows: PETS, then RAZER w_A = 0.5, on the final weights, without training.
    pets, razer = (r.metrics for r in reports[3:])
    assert pets["frozen/pets"] == 1 and razer["frozen/pets"] == 0 and razer["frozen/aleatoric_weight"] == 0.5
    assert pets["frozen/cost/c_A"] == 0 < razer["frozen/cost/c_A"] and pets["frozen/episodes"] == 3
    assert program.weights.version == 3  # no training after the iterations
    summary = reports[-1].summary
    assert summary["frozen/pets/success_rate"] == pets["frozen/success_rate"]
    assert summary["frozen_best_success_rate"] == razer["frozen/success_rate"]
    assert summary["final_dataset_size"] == 40 and "final_coverage" in summary and "final_return" in summary
    assert summary["final_success_rate_episodes"] == 2  # one planned episode per iteration: a rate of 2 episodes
    # Summary keys never collide with round keys (both go to one run, the summary at step 0).
    assert not set(summary) & {k for r in reports for k in r.metrics}


def test_frozen_episodes_fan_out_on_one_shared_weights_reference(tiny_run):
    _, program, _ = tiny_run
    planner = program.remote
    frozen_calls = [(member, args) for member, method, args in planner.calls if args[1].razer is not None]
    assert {member for member, _ in frozen_calls} == {0, 1}  # both actors took frozen episodes
    weights = {id(args[0]) for _, args in frozen_calls}
    assert len(weights) == 1 and {args[0].version for _, args in frozen_calls} == {3}
    assert [w.version for w in planner.shared if w is not None] == [3, 3]  # one share per frozen round
    # Every row plays the same episode seeds (common random numbers); planning calls got one episode each.
    trainer = program.trainer
    assert [method for _, method, _ in trainer.calls if method == "train"] == ["train"] * 3
    assert len(trainer.shared) == 3  # the dataset is shared once per training round


def test_rows_play_the_same_episode_seeds():
    trial = tiny_trial(iterations=0, frozen={"episodes": 2, "aleatoric_weights": [0.5]})
    program = build(trial, planners=2)
    local_jobs = []
    run_local = program.local.run_episode
    program.local.run_episode = lambda weights, job, on_step=None: (
        local_jobs.append(job) or run_local(weights, job, on_step)
    )
    try:
        run_rounds(program, range(program.total_rounds()))
        remote_jobs = [args[1] for _, method, args in program.remote.calls if method == "run_episode"]
        by_row = {}
        for job in local_jobs + remote_jobs:
            if job.razer is not None:
                by_row.setdefault(job.label, set()).add(job.seed)
        assert sorted(by_row) == ["pets", "razer_wA_0.5"]
        assert by_row["pets"] == by_row["razer_wA_0.5"] and len(by_row["pets"]) == 2
    finally:
        program.close()


class EagerGroup(RecordingGroup):
    """Role workers whose calls finish as soon as they are submitted, as actors that are ahead of the runner."""

    def submit(self, member, method, *args):
        pending = super().submit(member, method, *args)
        pending.result()
        return pending


@pytest.mark.parametrize(
    "group, expected", [(RecordingGroup, ["1/3", "2/3", "3/3"]), (EagerGroup, ["2/3", "3/3", "3/3"])]
)
def test_a_frozen_rows_progress_counts_the_planner_actors_episodes_as_they_finish(group, expected):
    """Three frozen episodes, two on the runner's worker and one on an actor: the count includes the actor's
    episode as soon as it is done (eager actor), and reaches 3/3 only at the row's end (actor still running)."""
    trial = tiny_trial(iterations=0, frozen={"episodes": 3, "pets": True, "aleatoric_weights": []})
    specs = MbrlProgram.roles_for(trial, 1, {"planner": 2})
    roles = {spec.name: group(spec.name, [spec.worker(**spec.kwargs) for _ in range(spec.count)]) for spec in specs}
    program = MbrlProgram(trial, roles, 1)
    try:
        program.run_round(0)
        shown = []
        set_progress = program.set_progress
        program.set_progress = lambda fraction, text: (shown.append((fraction, text)), set_progress(fraction, text))
        program.run_round(1)
        counts = [text.rsplit(": ", 1)[1].removesuffix(" episodes") for _, text in shown if text.endswith("episodes")]
        assert counts == expected
        fractions = [fraction for fraction, text in shown if text.endswith("episodes")]
        assert fractions == [int(c.split("/")[0]) / 3 for c in expected]
    finally:
        program.close()


def test_frozen_rows_run_the_task_with_their_own_options():
    """`frozen.task_options` changes the task of the frozen rows only: the loop's episodes keep their 10 steps,
    the frozen ones (on the runner's worker and on the actor) run 6, and the rows record it."""
    trial = tiny_trial(iterations=1, frozen={"episodes": 2, "pets": True, "task_options": {"episode_length": 6}})
    program = build(trial, planners=2)
    try:
        reports = run_rounds(program, range(program.total_rounds()))
        assert reports[1].metrics["steps"] == 10 and reports[1].metrics["dataset_size"] == 30
        frozen = reports[2].metrics
        assert frozen["frozen/mean_steps"] == 6 and frozen["frozen/episodes"] == 2
        remote = [args[1] for _, method, args in program.remote.calls if method == "run_episode"]
        assert [job.task_options for job in remote if job.razer is not None] == [{"episode_length": 6}]
        assert program.frozen_task.episode_length == 6 and program.task.episode_length == 10
    finally:
        program.close()


@pytest.mark.parametrize("release", ["1.1", "2.1"])
def test_random_episodes_draw_their_noise_as_the_planner_release(release):
    """The loop's colored-noise episodes follow ``planner.noise_release`` like the planner's samples."""
    from workers.dynamics.episodes import EpisodeJob, PlanningWorker, run_random_episode

    trial = tiny_trial(planner={**TINY["planner"], "noise_release": release})
    (planner,) = [role for role in MbrlProgram.roles_for(trial, 1, {"planner": 2}) if role.name == "planner"]
    worker = PlanningWorker(**planner.kwargs)
    try:
        actions = worker.run_episode(None, EpisodeJob(seed=3)).trajectory.actions
        other = {"1.1": "2.1", "2.1": "1.1"}[release]
        expected = {
            r: run_random_episode(worker.task, worker.env, 3, worker.random_beta, worker.random_scale, r)
            for r in (release, other)
        }
        np.testing.assert_array_equal(actions, expected[release].trajectory.actions)
        assert not np.allclose(actions, expected[other].trajectory.actions)
    finally:
        worker.close()


def test_each_frozen_row_draws_where_its_episodes_went(tiny_run):
    _, _, reports = tiny_run
    pets, razer = reports[3:]
    assert [a.path for a in pets.artifacts] == ["frozen/pets_episodes.csv", "plots/frozen_pets.png"]
    assert [a.path for a in razer.artifacts] == [
        "frozen/razer_wA_0.5_episodes.csv",
        "plots/frozen_razer_wA_0.5.png",
    ]
    assert all(a.data.startswith(b"\x89PNG") for a in pets.artifacts[1:] + razer.artifacts[1:])


def test_each_frozen_row_lists_its_episodes_so_that_rows_pair_by_seed(tiny_run):
    """The per-episode file of every row: the same seeds in the same order, and each line's ending and metrics
    are those of its episode (the row's logged rates are their means)."""
    import csv
    import io

    _, _, reports = tiny_run
    tables = []
    for report in reports[3:]:
        rows = list(csv.DictReader(io.StringIO(report.artifacts[0].data.decode())))
        tables.append(rows)
        assert [int(r["episode"]) for r in rows] == [0, 1, 2]
        assert np.mean([float(r["success"]) for r in rows]) == report.metrics["frozen/success_rate"]
        assert np.mean([float(r["falls"]) for r in rows]) == report.metrics["frozen/falls_rate"]
        assert np.mean([float(r["return"]) for r in rows]) == pytest.approx(report.metrics["frozen/mean_return"])
        endings = [episode_ending({k: float(r[k]) for k in ("success", "falls")}) for r in rows]
        assert [r["ending"] for r in rows] == endings
        assert all(math.isfinite(float(r["final_x"])) and math.isfinite(float(r["final_y"])) for r in rows)
    from workers.methods.mbrl import FROZEN, derived_seed

    trial = tiny_run[0]
    for rows in tables:  # the seeds the episodes were played with, so that rows and trials pair by them
        assert [int(r["seed"]) for r in rows] == [derived_seed(trial.seed, FROZEN, e) for e in range(3)]


def test_an_episodes_line_holds_its_ending_its_metrics_and_where_it_ended():
    """Episodes of known outcome: a success, a fall, one that ran out of time, each ending at its own place."""
    import csv
    import io

    from workers.data import Trajectory
    from workers.dynamics.episodes import EpisodeOutcome
    from workers.methods.mbrl import frozen_outcomes_csv

    def outcome(end_xy, metrics):
        observations = np.zeros((4, 10))
        observations[-1, :2] = end_xy
        return EpisodeOutcome(Trajectory(observations, np.zeros((3, 2)), np.zeros(3)), metrics, 1)

    outcomes = [
        outcome((12.5, 1.0), {"success": 1.0, "falls": 0.0, "return": 24.5}),
        outcome((-2.0, 2.5), {"success": 0.0, "falls": 1.0, "return": 8.0}),
        outcome((-9.0, 4.0), {"success": 0.0, "falls": 0.0}),  # a metric an episode lacks stays empty
    ]
    text = frozen_outcomes_csv([11, 22, 33], outcomes, make_task("bridge_maze")).decode()
    rows = list(csv.DictReader(io.StringIO(text)))
    assert [(r["seed"], r["ending"]) for r in rows] == [("11", "success"), ("22", "fall"), ("33", "neither")]
    assert [(float(r["final_x"]), float(r["final_y"])) for r in rows] == [(12.5, 1.0), (-2.0, 2.5), (-9.0, 4.0)]
    assert [r["return"] for r in rows] == ["24.5", "8.0", ""]


@pytest.mark.parametrize(
    "metrics, ending",
    [({"success": 1.0, "falls": 0.0}, "success"), ({"success": 0.0, "falls": 1.0}, "fall"), ({"success": 0.0}, "neither")],
)
def test_an_episode_ends_in_success_a_fall_or_neither(metrics, ending):
    assert episode_ending(metrics) == ending


def test_a_report_copies_the_visited_states_the_frozen_paths_and_the_newest_uncertainty_map():
    files = [
        "plots/uncertainty_v011.png",
        "plots/frozen_pets.png",
        "plots/uncertainty_v041.png",
        "plots/visited_states.png",
        "plots/uncertainty_v021.png",
        "plots/frozen_razer_wA_0.5.png",
        "plots/scratch.png",
    ]
    assert MbrlProgram.report_plots(files) == [
        "plots/frozen_pets.png",
        "plots/frozen_razer_wA_0.5.png",
        "plots/visited_states.png",
        "plots/uncertainty_v041.png",
    ]


def test_model_artifact_loads_with_the_documented_one_liner(tiny_run, tmp_path):
    _, program, reports = tiny_run
    paths = [a.path for r in reports for a in r.artifacts]
    assert paths[:5] == [
        "models/model_v002.npz",
        "plots/uncertainty_v002.png",
        "models/model_v003.npz",
        "plots/uncertainty_v003.png",
        "plots/visited_states.png",
    ]
    artifact = reports[2].artifacts[0]
    (tmp_path / "model.npz").write_bytes(artifact.data)
    model = DynamicsEnsemble.load(tmp_path / "model.npz")  # the one-liner of the README
    assert model.weights_version == 3 and model.obs_dim == 10
    reference = program.weights.model()
    inputs = np.random.default_rng(0).normal(size=(5, 7, 12)).astype(np.float32)
    import torch

    for ours, theirs in zip(model.predict(torch.from_numpy(inputs)), reference.predict(torch.from_numpy(inputs))):
        torch.testing.assert_close(ours, theirs, rtol=0, atol=0)
    assert all(a.data.startswith(b"\x89PNG") for a in reports[2].artifacts[1:])


def test_a_refit_trains_the_last_model_more_before_the_frozen_rows_and_they_plan_on_it():
    """frozen.refit_epochs: one more training round, after the iterations and before the rows, of the given
    epochs on the whole dataset (nothing held out); its model is logged, and the rows plan with its weights."""
    frozen = {"episodes": 2, "aleatoric_weights": [0.5], "refit_epochs": 3}
    trial = tiny_trial(iterations=1, model_every=0, frozen=frozen)
    assert MbrlProgram.planned_rounds(trial) == 1 + 1 + 1 + 2
    assert MbrlProgram.round_work(trial, {"planner": 2}) == [0.0, 1.0, 0.0, 1.0, 1.0]
    program = build(trial, planners=2)
    reports = run_rounds(program, range(MbrlProgram.planned_rounds(trial)))
    loop, refit = reports[1], reports[2]
    assert [r.step for r in reports] == [0, 1, 2, 0, 1]
    assert loop.metrics["weights_version"] == 2 and refit.metrics["refit/weights_version"] == 3
    assert "held_out_nll" in loop.metrics and "refit/held_out_nll" not in refit.metrics
    assert not {k for k in refit.metrics if not k.startswith("refit/") and k != "round_seconds"}
    train_calls = [args for _, method, args in program.trainer.calls if method == "train"]
    assert [args[-1] for args in train_calls] == [None, None, 3]  # the refit's epochs, the loop's own otherwise
    # The same dataset as the last iteration's: 3 epochs against the model's 2 take half as many steps again.
    assert refit.metrics["refit/gradient_steps"] == 1.5 * loop.metrics["gradient_steps"]
    # The loop's last model and the refit model are both logged; the visited states once, with the loop's.
    assert [a.path for a in loop.artifacts] == [
        "models/model_v002.npz",
        "plots/uncertainty_v002.png",
        "plots/visited_states.png",
    ]
    assert [a.path for a in refit.artifacts] == ["models/model_v003.npz", "plots/uncertainty_v003.png"]
    frozen_calls = [args for _, _, args in program.remote.calls if args[1].razer is not None]
    assert len(frozen_calls) == 2 and {args[0].version for args in frozen_calls} == {3}  # one episode per row
    program.close()


def test_a_refit_needs_frozen_rows_and_data_to_train_on():
    with pytest.raises(ValidationError, match="refit_epochs"):
        MbrlSettings.model_validate(TINY | {"frozen": {"episodes": 0, "refit_epochs": 10}})
    with pytest.raises(ValidationError, match="refit_epochs"):
        frozen = TINY["frozen"] | {"refit_epochs": 5}
        MbrlSettings.model_validate(
            TINY | {"random_episodes": 0, "iterations": 0, "initial_model": "m.npz", "frozen": frozen}
        )
    with pytest.raises(ValidationError, match="greater than or equal to 0"):
        MbrlSettings.model_validate(TINY | {"frozen": TINY["frozen"] | {"refit_epochs": -1}})


def test_checkpoint_round_trip_continues_identically():
    """Stop after round 1, restore a fresh program (fresh roles) from the checkpoint bytes, go on: same results."""
    trial = tiny_trial(frozen={"episodes": 2, "aleatoric_weights": [0.5]})
    straight = build(trial)
    expected = run_rounds(straight, range(straight.total_rounds()))
    straight.close()

    first = build(trial)
    run_rounds(first, range(2))
    data = checkpoint.to_bytes({"program": first.state_dict()})
    first.close()
    second = build(trial)
    second.load_state_dict(checkpoint.from_bytes(data)["program"])
    resumed = run_rounds(second, range(2, second.total_rounds()))
    second.close()
    assert second.buffer.steps == straight.buffer.steps
    for got, want in zip(resumed, expected[2:]):
        assert got.metrics.keys() == want.metrics.keys()
        for key in got.metrics:
            if "seconds" not in key:
                assert got.metrics[key] == want.metrics[key], key
    assert {k: v for k, v in resumed[-1].summary.items() if "seconds" not in k} == {
        k: v for k, v in expected[-1].summary.items() if "seconds" not in k
    }


def test_a_loaded_model_is_scored_on_round_zeros_episodes_before_it_trains_on_them(tiny_run, tmp_path):
    """Fine-tuning an initial model: its held-out NLL on the random episodes is what it had learned before;
    a fresh model's round 0 holds nothing out."""
    _, program, reports = tiny_run
    assert "held_out_nll" not in reports[0].metrics
    path = tmp_path / "model.npz"
    path.write_bytes(reports[2].artifacts[0].data)
    loaded = build(tiny_trial(model={}, initial_model=str(path), random_episodes=1, iterations=1))
    try:
        (first,) = run_rounds(loaded, [0])
        assert math.isfinite(first.metrics["held_out_nll"]) and math.isfinite(first.metrics["held_out_mse"])
    finally:
        loaded.close()


def test_a_frozen_only_trial_evaluates_a_saved_model(tiny_run, tmp_path):
    _, program, reports = tiny_run
    path = tmp_path / "model.npz"
    path.write_bytes(reports[2].artifacts[0].data)
    trial = tiny_trial(
        model={}, initial_model=str(path), random_episodes=0, iterations=0, frozen={"episodes": 2, "pets": True}
    )
    assert MbrlProgram.roles_for(trial, 1, {}) == []  # nothing to train: no trainer
    assert MbrlProgram.runner_cpus(trial, 1) == 1 and trial.settings.model.hidden_size == 16
    frozen = build(trial)
    try:
        results = run_rounds(frozen, range(frozen.total_rounds()))
        assert results[0].metrics["initial_model_version"] == 3
        assert results[1].metrics["frozen/episodes"] == 2
        state = checkpoint.from_bytes(checkpoint.to_bytes({"program": frozen.state_dict()}))["program"]
        assert state["weights"]["version"] == 3
    finally:
        frozen.close()


def test_roles_take_turns_on_one_unit():
    trial = tiny_trial()
    (trainer,) = MbrlProgram.roles_for(trial, 2, {})
    assert trainer.name == "trainer" and trainer.stateful and trainer.cpus == 1 and trainer.kwargs["cpus"] == 2
    assert MbrlProgram.runner_cpus(trial, 2) == 1
    roles = MbrlProgram.roles_for(trial, 1, {"planner": 3})
    planner = next(r for r in roles if r.name == "planner")
    assert planner.count == 2 and not planner.stateful and planner.cpus == 1


# -------------------------------------------------------------- bad input
def write(tmp_path: Path, name: str, text: str) -> Path:
    path = tmp_path / f"{name}.yaml"
    path.write_text(text)
    return path


HEADER = "name: bad\ntask: bridge_maze\nmethod: mbrl\n"
BAD_INPUT = {
    # name: (sweep text after the header, expected line, path fragment, message fragment)
    "preset_of_another_state": ("base:\n  model:\n    preset: noisy_halfcheetah\n", 6, "model.preset", "17-d state"),
    "box_outside_the_state": (
        "base:\n  razer:\n    safety_weight: 10\n    safety_boxes:\n      - dims: [2, 10]\n        low: [null, 0]\n"
        "        high: [-1.5, null]\n",
        7,
        "razer.safety_boxes.0.dims",
        "state dimension 10",
    ),
    "negative_weight": (
        "base:\n  razer:\n    aleatoric_weight: -0.5\n",
        6,
        "base.razer.aleatoric_weight",
        "greater than or equal to 0",
    ),
    "negative_swept_weight": (
        "parameters:\n  razer.epistemic_weight:\n    values: [0.05, -1]\n",
        5,
        "razer.epistemic_weight",
        "greater than or equal to 0",
    ),
    "delta_one": ("base:\n  razer:\n    safety_delta: 1.0\n", 6, "base.razer.safety_delta", "less than 1"),
    "delta_zero": ("base:\n  razer:\n    safety_delta: 0\n", 6, "base.razer.safety_delta", "greater than 0"),
    "negative_frozen_weight": (
        "base:\n  frozen:\n    episodes: 25\n    aleatoric_weights: [0.1, -0.1]\n",
        7,
        "base.frozen.aleatoric_weights",
        ">= 0",
    ),
    "frozen_option_the_task_lacks": (
        "base:\n  frozen:\n    episodes: 25\n    task_options:\n      episode_lenght: 200\n",
        8,
        "frozen.task_options.episode_lenght",
        "bridge_maze has no option 'episode_lenght' (did you mean 'episode_length'?); its options: ",
    ),
    "frozen_option_out_of_range": (
        "base:\n  frozen:\n    episodes: 25\n    task_options:\n      episode_length: 0\n",
        8,
        "frozen.task_options.episode_length",
        "greater than or equal to 1",
    ),
    "negative_uncertainty_dimension": (
        "base:\n  razer:\n    uncertainty_dims: [0, -2]\n",
        6,
        "razer.uncertainty_dims.1",
        "greater than or equal to 0",
    ),
    "uncertainty_dimension_twice": (
        "base:\n  razer:\n    uncertainty_dims: [3, 1, 3]\n",
        6,
        "razer.uncertainty_dims",
        "a dimension is listed twice in [3, 1, 3]",
    ),
    "safety_without_box": ("base:\n  razer:\n    safety_weight: 5\n", 6, "razer.safety_weight", "has none of its own"),
    "unknown_role": (
        "resources:\n  workers:\n    trainers: 2\n",
        6,
        "resources.workers.trainers",
        "did you mean 'trainer'",
    ),
}


def test_a_model_field_set_to_null_is_passed_on_and_an_unset_one_takes_the_preset(tmp_path):
    """`state_margin: null` switches the state clamp off (the trainer's config carries None, also after the
    trial is rebuilt from its record); a sweep that does not mention it keeps the default clamp."""
    from orchestrator.sweep import TrialConfig, load_sweep

    off = write(tmp_path, "off", HEADER + "base:\n  model:\n    preset: small\n    state_margin: null\n")
    on = write(tmp_path, "on", HEADER + "base:\n  model:\n    preset: small\n")
    (trial_off,), (trial_on,) = load_sweep(off).trials, load_sweep(on).trials
    assert trial_off.config.settings.model.state_margin is None
    assert TrialConfig.from_canonical(trial_off.config.canonical()).settings.model.state_margin is None
    assert trial_on.config.settings.model.state_margin == 0.25
    assert trial_off.key != trial_on.key


def validate(sweep: Path, capsys) -> tuple[int, str]:
    """``icemlab validate SWEEP`` in this process: (exit code, stderr)."""
    from orchestrator.cli import main

    with pytest.raises(SystemExit) as exit_:
        main(["validate", str(sweep)])
    return exit_.value.code, capsys.readouterr().err


@pytest.mark.parametrize("case", sorted(BAD_INPUT))
def test_bad_input_gives_a_located_error_through_validate(case, tmp_path, capsys):
    body, line, path, message = BAD_INPUT[case]
    sweep = write(tmp_path, case, HEADER + body)
    code, err = validate(sweep, capsys)
    assert code == 2, err
    first = err.splitlines()[0]
    assert first.startswith(f"{sweep}:{line}: ") and path in first and message in first, first
    assert "nothing was started" in err


def test_the_cli_process_refuses_a_preset_of_another_state(tmp_path):
    sweep = write(tmp_path, "preset", HEADER + BAD_INPUT["preset_of_another_state"][0])
    result = cli("validate", str(sweep), cwd=tmp_path, timeout=120)
    assert result.returncode == 2 and f"{sweep}:6: model.preset: preset 'noisy_halfcheetah'" in result.stderr


def test_a_model_file_of_another_task_is_refused(tmp_path, capsys):
    from workers.dynamics.settings import EnsembleConfig

    cheetah = DynamicsEnsemble(17, 6, EnsembleConfig.preset("small", hidden_size=8))
    cheetah.save(tmp_path / "cheetah.npz", weights_only=True)
    sweep = write(
        tmp_path, "mismatch", HEADER + f"base:\n  initial_model: {tmp_path / 'cheetah.npz'}\n  random_episodes: 0\n"
    )
    code, err = validate(sweep, capsys)
    assert code == 2 and f"{sweep}:5: initial_model:" in err and "17-d state" in err


def test_a_ground_truth_task_is_refused_for_mbrl_and_a_model_task_for_mpc(tmp_path, capsys):
    for name, text, fragment in (
        ("gt", "name: gt\ntask: halfcheetah_running\nmethod: mbrl\n", "ground-truth task of method mpc"),
        ("mb", "name: mb\ntask: bridge_maze\n", "MuJoCo ground-truth task"),
    ):
        code, err = validate(write(tmp_path, name, text), capsys)
        assert code == 2 and fragment in err, err


def test_a_rule_across_fields_is_checked_per_trial_where_a_variant_can_meet_it(tmp_path, capsys):
    """The base alone has no data to learn from; a variant that collects some makes a valid trial, and a variant
    that does not is refused at the base's line."""
    base = "base:\n  random_episodes: 0\n  frozen:\n    episodes: 2\n"
    from orchestrator.sweep import load_sweep

    met = write(tmp_path, "met", HEADER + base + "variants:\n  - name: collects\n    random_episodes: 1\n")
    (trial,) = load_sweep(met).trials
    assert trial.config.settings.random_episodes == 1
    unmet = write(tmp_path, "unmet", HEADER + base + "variants:\n  - name: more_particles\n    particles: 3\n")
    code, err = validate(unmet, capsys)
    assert code == 2 and err.startswith(f"{unmet}:4: base: random_episodes is 0 and there is no initial_model"), err


def test_task_options_are_validated_like_every_task(tmp_path, capsys):
    sweep = write(tmp_path, "wind", HEADER + "base:\n  task_options:\n    wind_max: -3\n    gust: 1\n")
    code, err = validate(sweep, capsys)
    assert code == 2
    assert "task_options.wind_max" in err and "bridge_maze has no option 'gust'" in err


# ------------------------------------------------------------------ reports
class Run:
    def __init__(self, values, params=None):
        self.values = values
        self.params = params or {}


def test_report_plots_success_against_the_aleatoric_weight_and_failure_against_noise(tmp_path):
    from orchestrator import report_mbrl
    from orchestrator.report import Group, Summary
    from orchestrator.statistics import Interval

    def trial(pets, razer_a, razer_b, coverage, wind):
        values = {"final_coverage": coverage}
        for row, success, weight in (("pets", pets, 0.0), ("razer_wA_0.1", razer_a, 0.1), ("razer_wA_1", razer_b, 1.0)):
            values |= {f"frozen/{row}/success_rate": success, f"frozen/{row}/aleatoric_weight": weight,
                       f"frozen/{row}/falls_rate": 1 - success, f"frozen/{row}/pets": float(row == "pets")}  # fmt: skip
        return Run(values, {"task_options.wind_max": str(wind)})

    nothing = Interval(0.0, 0.0, 0.0)
    groups = [
        Group(
            "bridge_maze",
            "mbrl",
            {},
            None,
            setting,
            trials,
            0.0,
            0.0,
            nothing,
            None,
            None,
            None,
            None,
        )  # fmt: skip
        for setting, trials in (
            ({"task_options.wind_max": 10}, [trial(0.6, 0.8, 0.9, 0.1, 10), trial(0.5, 0.9, 1.0, 0.2, 10)]),
            ({"task_options.wind_max": 30}, [trial(0.2, 0.7, 0.9, 0.1, 30)]),
            ({}, [trial(0.4, 0.8, 0.9, 0.1, 20.0)]),  # ran the default wind: placed by its logged setting
        )
    ]
    summary = Summary(groups, "frozen_success", "frozen_best_success_rate", "max", 0)
    points = report_mbrl.frozen_points(groups[0].trials)
    assert [(p.row, p.pets, p.aleatoric_weight) for p in points] == [
        ("pets", True, 0.0),
        ("razer_wA_0.1", False, 0.1),
        ("razer_wA_1", False, 1.0),
    ]
    mean, sem, n = points[1].values["success_rate"]
    assert (mean, n) == (pytest.approx(0.85), 2) and sem == pytest.approx(0.05)
    success = report_mbrl.success_figure(summary)
    (line, *_) = success.axes[0].lines
    assert list(line.get_xdata()) == [0.1, 1.0]
    failures = report_mbrl.drop_rate_figure(summary)
    labels = sorted(text.get_text() for text in failures.axes[0].get_legend().get_texts())
    assert labels == ["pets", "razer_wA_0.1", "razer_wA_1"]
    assert "against wind_max" in failures.axes[0].get_title()  # the option the rows are placed by, named
    pets = next(bars.lines[0] for bars in failures.axes[0].containers if bars.get_label() == "pets")
    assert list(pets.get_xdata()) == [10, 20, 30]
    assert list(pets.get_ydata()) == pytest.approx([0.45, 0.6, 0.8])
    written = report_mbrl.write_files(summary, tmp_path)
    assert [p.name for p in written] == ["frozen_success.png", "failure_rate.png", "coverage.png"]


def test_the_success_figure_draws_the_two_readings_of_var_a_as_two_lines():
    from orchestrator import report_mbrl
    from orchestrator.report import Group, Summary
    from orchestrator.statistics import Interval

    values = {}
    for row, success, weight in (("pets", 0.2, 0.0), ("razer_wA_0.25", 0.3, 0.25), ("razer_wA_0.5", 0.1, 0.5),
                                 ("razer_wA_0.25_means", 0.9, 0.25), ("razer_wA_0.5_means", 0.8, 0.5)):  # fmt: skip
        values |= {f"frozen/{row}/success_rate": success, f"frozen/{row}/aleatoric_weight": weight}
    nothing = Interval(0.0, 0.0, 0.0)
    group = Group("bridge_maze", "mbrl", {}, None, {}, [Run(values)], 0.0, 0.0, nothing, None, None, None, None)
    points = report_mbrl.frozen_points(group.trials)
    assert [(p.row, p.aleatoric_states) for p in points] == [
        ("pets", "particles"),
        ("razer_wA_0.25", "particles"),
        ("razer_wA_0.5", "particles"),
        ("razer_wA_0.25_means", "means"),
        ("razer_wA_0.5_means", "means"),
    ]
    figure = report_mbrl.success_figure(Summary([group], "frozen_success", "frozen_best_success_rate", "max", 0))
    lines = [line for line in figure.axes[0].lines if line.get_marker() in ("o", "s")]
    assert [list(line.get_ydata()) for line in lines] == [[0.3, 0.1], [0.9, 0.8]]
    legend = [text.get_text() for text in figure.axes[0].get_legend().get_texts()]
    assert sum("Var_A at mean states" in text for text in legend) == 1


# ---------------------------------------------------------------- sweeps
def test_smoke_and_paper_sweeps_validate():
    from orchestrator.sweep import load_sweep

    smoke = load_sweep(ROOT / "sweeps/smoke/mbrl.yaml")
    (trial,) = smoke.trials
    spec = trial.config.spec()
    assert MbrlProgram.planned_rounds(spec) >= 2 and trial.config.settings.model.preset == "small"
    roles = {r.name for r in MbrlProgram.roles_for(spec, 1, smoke.sweep.resources.workers)}
    assert roles == set(MbrlProgram.role_names)  # the smoke run exercises every role
    paper = load_sweep(ROOT / "sweeps/paper/razer_bridge_maze.yaml")
    settings = paper.trials[0].config.settings
    assert settings.razer.epistemic_weight == 0.05 and settings.frozen.episodes >= 25 and settings.frozen.pets
    assert len(settings.frozen.aleatoric_weights) >= 3 and settings.model.preset == "bridge_maze"
    cheetah = load_sweep(ROOT / "sweeps/paper/razer_noisy_halfcheetah.yaml").trials
    assert cheetah[0].config.settings.model.preset == "noisy_halfcheetah"
    # D.1.5: PETS plans with the same hard-violation penalty as every other row.
    assert {t.config.settings.task_options["ceiling_cost"] for t in cheetah} == {50}


def test_method_is_registered():
    assert METHODS["mbrl"] is MbrlProgram and MbrlProgram.role_names == ("trainer", "planner")


# -------------------------------------------------- through the CLI (slow)
@pytest.mark.slow
def test_smoke_sweep_runs_through_the_cli(tmp_path):
    from helpers import sweep_runs

    from orchestrator.tracking import FINISHED, Tracker, default_tracking_uri

    result = cli("run", str(ROOT / "sweeps/smoke/mbrl.yaml"), "--quiet", cwd=tmp_path, timeout=600)
    assert result.returncode == 0, result.stderr
    parent, (child,) = sweep_runs(default_tracking_uri(tmp_path), "smoke_mbrl")
    assert parent.status == FINISHED and child.status == FINISHED
    tracker = Tracker(default_tracking_uri(tmp_path))
    assert [s for s, _ in tracker.metric_history(child.run_id, "icemlab.round")] == [0, 1, 2, 3, 4]
    assert [v for _, v in sorted(tracker.metric_history(child.run_id, "weights_version"))] == [1, 2, 3]
    assert [v for _, v in sorted(tracker.metric_history(child.run_id, "planned_with_version"))] == [1, 2]
    assert "frozen/pets/success_rate" in child.metrics and "final_coverage" in child.metrics
    assert {"models", "plots", "checkpoints"} <= set(tracker.list_files(child.run_id))
    assert "frozen_success.png" in tracker.list_files(parent.run_id)
    report = cli("report", str(ROOT / "sweeps/smoke/mbrl.yaml"), "--output", "out", cwd=tmp_path, timeout=300)
    assert report.returncode == 0, report.stderr
    (folder,) = (tmp_path / "out" / "trials").iterdir()
    copied = sorted(p.name for p in folder.iterdir())
    assert "visited_states.png" in copied and any(name.startswith("uncertainty_v") for name in copied)


# ------------------------------------------------- service faults (slow)
FAULT_BASE: dict[str, Any] = {
    "task_options": {"episode_length": 15},
    # Many small minibatches: a training call lasts a few seconds, long enough to be killed in.
    "model": {"preset": "small", "hidden_size": 16, "hidden_layers": 2, "epochs": 400, "batch_size": 8},
    "planner": {"population": 12, "iterations": 2, "horizon": 4, "elites": 4},
    "razer": {"epistemic_weight": 0.05},
    "random_episodes": 1,
    "iterations": 3,
}


def fault_sweep(directory: Path, name: str, **changes: Any) -> Path:
    sweep = {
        "name": name,
        "task": "bridge_maze",
        "method": "mbrl",
        "base": FAULT_BASE | changes,
        "seeds": [0],
        # One thread everywhere, as in run_locally: results can be compared bit for bit.
        "resources": {"threads_per_worker": 1},
    }
    path = directory / f"{name}.yaml"
    path.write_text(yaml.safe_dump(sweep, sort_keys=False))
    return path


def uninterrupted(sweep: Path) -> list:
    from orchestrator.sweep import load_sweep
    from workers.methods import run_locally

    return run_locally(MbrlProgram, load_sweep(sweep).trials[0].config.spec())


def history(tracker, run_id: str, key: str) -> list[tuple[int, float]]:
    return sorted(tracker.metric_history(run_id, key))


@pytest.fixture
def local_ray():
    import ray

    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    yield
    ray.shutdown()


@pytest.mark.slow
def test_killed_trainer_mid_training_resumes_from_the_last_checkpoint(tmp_path, local_ray):
    """SIGKILL the EnsembleTrainer inside a training call: the round is lost, the loop goes on from the last
    checkpoint (weights, Adam state and dataset restored) and ends as an uninterrupted run."""
    import os
    import signal
    import threading
    import time

    import ray
    from helpers import sweep_runs, wait_for

    from orchestrator.scheduler import SweepScheduler
    from orchestrator.sweep import load_sweep
    from orchestrator.tracking import FINISHED, Tracker, default_tracking_uri

    sweep = fault_sweep(tmp_path, "trainer_kill")
    tracker = Tracker(default_tracking_uri(tmp_path))
    scheduler = SweepScheduler(load_sweep(sweep), tracker)
    killed = {}

    def kill_trainer_while_it_trains():
        def running():
            active = scheduler._active
            return active[0] if active and active[0].phase == "running" else None

        # The pid first: an iteration's planning can be shorter than the scheduler's progress poll, so the
        # only phase the test waits to see is a training call (seconds long), in round 2 or later.
        attempt = wait_for(running, timeout=300, interval=0.05, what="the trial running")
        pid = ray.get(attempt.group.workers["trainer"][0].pid.remote(), timeout=120)

        def training_in_a_later_round():
            text = attempt.progress.get("text", "")
            return attempt.round_index >= 2 and text.startswith(f"round {attempt.round_index}: training")

        wait_for(training_in_a_later_round, timeout=300, interval=0.02, what="training in round 2 or later")
        time.sleep(0.3)
        os.kill(pid, signal.SIGKILL)
        killed.update(pid=pid, round=attempt.round_index)

    killer = threading.Thread(target=kill_trainer_while_it_trains, daemon=True)
    killer.start()
    outcome = scheduler.run()
    killer.join(timeout=5)
    assert killed, "the trainer was never killed"
    assert (outcome.finished, outcome.failed) == (1, 0)

    _, (child,) = sweep_runs(tracker.uri, "trainer_kill")
    assert child.status == FINISHED and child.attempts == 1  # recovered in place: no new actor group
    assert child.metrics["recovered/lost_process"] == 1.0 and "failures/lost_process" not in child.metrics
    assert [s for s, _ in history(tracker, child.run_id, "icemlab.round")] == [0, 1, 2, 3]  # each round once
    assert [v for _, v in history(tracker, child.run_id, "weights_version")] == [1, 2, 3, 4]
    expected = uninterrupted(sweep)
    for key in ("dataset_size", "episode_return", "train_nll", "held_out_nll"):
        got = [v for _, v in history(tracker, child.run_id, key)]
        assert got == [r.metrics[key] for r in expected if key in r.metrics], key


@pytest.mark.slow
def test_driver_sigkill_then_resume_continues_with_the_same_dataset(tmp_path):
    """Kill the driver mid-trial; --resume continues from the last completed iteration, nothing twice."""
    import os
    import signal
    from collections import Counter

    from helpers import kill_group, start_cli, sweep_runs, wait_for

    from orchestrator.tracking import FINISHED, RUNNING, Tracker, default_tracking_uri

    sweep = fault_sweep(tmp_path, "crash", iterations=4, model={**FAULT_BASE["model"], "epochs": 20})
    uri = default_tracking_uri(tmp_path)
    tracker = Tracker(uri)
    driver = start_cli("run", str(sweep), "--quiet", cwd=tmp_path)
    try:

        def two_rounds_in():
            _, children = sweep_runs(uri, "crash")
            running = [c for c in children if c.status == RUNNING]
            return running and len(tracker.logged_rounds(running[0].run_id)) >= 2

        wait_for(two_rounds_in, timeout=300, what="a trial two rounds in")
        os.kill(driver.pid, signal.SIGKILL)  # the driver only; its Ray processes are orphaned
        driver.wait(timeout=30)
    finally:
        kill_group(driver)
    _, (before,) = sweep_runs(uri, "crash")
    assert before.status == RUNNING
    done_before = len(tracker.logged_rounds(before.run_id))

    result = cli("run", str(sweep), "--resume", "--quiet", cwd=tmp_path, timeout=600)
    assert result.returncode == 0, result.stderr
    _, (after,) = sweep_runs(uri, "crash")
    assert after.run_id == before.run_id and after.status == FINISHED and after.attempts == 2
    assert [s for s, _ in history(tracker, after.run_id, "icemlab.round")] == list(range(5))
    for key in ("dataset_size", "episode_return", "weights_version"):
        steps = [s for s, _ in history(tracker, after.run_id, key)]
        assert not [s for s, n in Counter(steps).items() if n > 1], key  # no step logged twice
    expected = uninterrupted(sweep)
    # The dataset after every iteration is the uninterrupted run's: the resumed rounds start from the same one.
    assert [v for _, v in history(tracker, after.run_id, "dataset_size")] == [
        r.metrics["dataset_size"] for r in expected
    ]
    assert [v for _, v in history(tracker, after.run_id, "episode_return")] == [
        r.metrics["episode_return"] for r in expected
    ]
    assert after.metrics["final_return"] == expected[-1].summary["final_return"]
    assert 2 <= done_before < 5


def test_trainer_holds_out_the_newest_episode_before_training_on_it():
    from workers.dynamics.ensemble import Transitions
    from workers.dynamics.settings import EnsembleConfig
    from workers.dynamics.trainer import EnsembleTrainer

    rng = np.random.default_rng(0)
    obs, act = rng.normal(size=(60, 3)), rng.uniform(-1, 1, size=(60, 2))
    data = Transitions(obs, act, obs + 0.1 * act[:, [0, 1, 0]])
    config = EnsembleConfig.preset("small", hidden_size=8, epochs=3).model_dump()
    trainer = EnsembleTrainer(3, 2, config, seed=0)
    first = trainer.train(Transitions(*(x[:40] for x in data)), 40, seed=1)
    assert "held_out_nll" not in first.metrics and first.weights.version == 1  # untrained: nothing to hold out
    before = first.weights.model().evaluate(Transitions(*(x[40:] for x in data)))
    second = trainer.train(data, 40, seed=2)
    assert (second.metrics["held_out_nll"], second.metrics["held_out_mse"]) == pytest.approx(before[:2], rel=1e-6)
    assert second.metrics["weights_version"] == 2 and second.weights.version == 2
    # State out, state in: a fresh trainer continues identically (weights, Adam moments, version).
    copy = EnsembleTrainer(3, 2, config, seed=5)
    copy.load_state_dict(checkpoint.from_bytes(checkpoint.to_bytes(trainer.state_dict())))
    ours, theirs = copy.train(data, 40, seed=3).metrics, trainer.train(data, 40, seed=3).metrics
    assert {k: v for k, v in ours.items() if k != "train_seconds"} == {
        k: v for k, v in theirs.items() if k != "train_seconds"
    }


@pytest.mark.slow
def test_noisy_halfcheetah_reduced_run_logs_return_and_violation_curves():
    """Noisy-HalfCheetah (Fig. 36), cut down: the loop with the aleatoric penalty and the ceiling's safety term."""
    trial = tiny_trial(
        task="noisy_halfcheetah",
        task_options={"episode_length": 30, "velocity_threshold": 0.5},
        model={"preset": "small", "hidden_size": 32, "epochs": 5},
        planner={"population": 24, "iterations": 2, "horizon": 8},
        razer={"aleatoric_weight": 0.05, "safety_weight": 50.0, "safety_delta": 0.05},
        random_episodes=1,
        iterations=3,
        frozen={"episodes": 0},
    )
    assert [box.dims for box in trial.settings.razer.safety_boxes] == [(0,)]  # the ceiling, from the task
    program = build(trial)
    try:
        reports = run_rounds(program, range(program.total_rounds()))
    finally:
        program.close()
    iterations = [r.metrics for r in reports[1:]]
    for metrics in iterations:
        for key in ("episode_return", "safety_violations", "ceiling_violations", "noisy_steps", "cost/c_S", "cost/c_A"):
            assert math.isfinite(metrics[key]), key
        assert metrics["steps"] == 30 and metrics["cost/c_A"] > 0
    assert "coverage" not in iterations[0]  # no coverage grid for this task
    assert reports[-1].summary["final_return"] == pytest.approx(np.mean([m["episode_return"] for m in iterations]))


def test_a_row_without_a_finite_rate_in_any_seed_draws_no_bar_and_breaks_no_report():
    from orchestrator import report_mbrl

    (point,) = report_mbrl.frozen_points([Run({"frozen/razer_wA_1/success_rate": math.nan,
                                               "frozen/razer_wA_1/episodes": 25.0})])  # fmt: skip
    assert point.values["success_rate"][2] == 0
    assert report_mbrl._rate_error(point, "success_rate") == (0.0, 0.0)
