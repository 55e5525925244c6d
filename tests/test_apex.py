"""APEX (chapter 4) in-process: adaptive lambda, iCEM_pi, observations, policy, relabeling, the program.

Service tests (Ray, MLflow, faults) are in tests/test_apex_service.py. The Fig. 9 mechanism needs an
expert episode and a trained policy on Fetch and takes minutes: marker slow.
"""

from __future__ import annotations

import math

import os
from pathlib import Path

import numpy as np
import pytest
from helpers import cli

from orchestrator.sweep import SweepError, load_sweep
from workers import checkpoint
from workers.methods import METHODS, LocalRoleGroup, TrialSpec, run_locally
from workers.methods.apex import ApexProgram, ApexSettings, derived_seed
from workers.planning import PlannerConfig
from workers.planning.icem import CostBatch
from workers.policy import (
    GUIDANCE,
    AuxiliaryTerm,
    ExpertSettings,
    GuidedObjective,
    ObservationReader,
    Policy,
    PolicyTrainer,
    PolicyWeights,
    RelabelWorker,
    load_policy,
)
from workers.policy.expert import relabel_seed
from workers.tasks import make_task

ROOT = Path(__file__).resolve().parents[1]


# ----------------------------------------------------------------- fixtures
@pytest.fixture(scope="module")
def workers():
    """task name -> a RelabelWorker (its envs and planning model), built on first use."""
    cache: dict[str, RelabelWorker] = {}

    def get(name: str) -> RelabelWorker:
        if name not in cache:
            cache[name] = RelabelWorker(name)
        return cache[name]

    yield get
    for worker in cache.values():
        worker.close()


def random_policy(worker: RelabelWorker, seed: int = 0) -> Policy:
    observation, _ = worker.scratch.reset(seed=0)
    obs_dim = len(worker.task.observe(observation))
    return Policy(
        PolicyTrainer(seed, obs_dim=obs_dim, action_dim=worker.task.action_dim, task=worker.task.name).weights()
    )


def expert_settings(task_name: str, budget: int = 45, horizon: int = 10, **switches) -> ExpertSettings:
    planner = PlannerConfig(budget=budget, horizon=horizon).resolved(make_task(task_name).colored_noise_beta)
    return ExpertSettings(planner=planner, **switches)


def start(worker: RelabelWorker, seed: int = 1):
    """The worker's real environment reset with ``seed``: (state, observation)."""
    observation, _ = worker.env.reset(seed=seed)
    return worker.task.capture(worker.env), worker.task.observe(observation)


# ------------------------------------------------------- adaptive lambda
def objective(c: float = 0.025, epsilon: float = 1e-6, adaptive: bool = True, elites: int = 4) -> GuidedObjective:
    return GuidedObjective(elites, [AuxiliaryTerm(GUIDANCE, adaptive, c, 2.0)], epsilon)


def test_lambda_is_zero_when_the_main_cost_is_flat_among_the_elites():
    # The four best samples tie on J (nothing found yet); worse ones differ. The guidance varies.
    main = np.array([5.0, 5.0, 7.0, 5.0, 9.0, 5.0])
    guidance = np.array([3.0, 0.1, 2.0, 8.0, 1.0, 4.0])
    rank = objective()
    costs = rank(CostBatch(main, components={GUIDANCE: guidance}), 0)
    assert rank.records[-1].lambdas[GUIDANCE] == 0.0 and rank.records[-1].main_range == 0.0
    np.testing.assert_array_equal(costs, main)  # the weak policy cannot steer the search


def test_lambda_times_the_auxiliary_range_is_c_times_the_main_range():
    rng = np.random.default_rng(0)
    main, guidance = rng.normal(10, 3, 25), rng.uniform(0, 50, 25)
    rank = objective(c=0.025, epsilon=1e-12, elites=10)
    rank(CostBatch(main, components={GUIDANCE: guidance}), 1)
    elites = np.argsort(main, kind="stable")[:10]  # the preliminary elite set: best by J
    weight = rank.records[-1].lambdas[GUIDANCE]
    assert weight * np.ptp(guidance[elites]) == pytest.approx(0.025 * np.ptp(main[elites]), rel=1e-9)
    assert rank.records[-1].main_range == pytest.approx(np.ptp(main[elites]))


def test_a_diverged_sample_among_the_elites_counts_in_neither_range():
    """Fewer finite costs than K: the non-finite sample's guidance distance must not widen R(C) (eq. 17)."""
    main = np.array([1.0, 3.0, np.inf, np.nan])
    guidance = np.array([2.0, 4.0, 100.0, 0.0])
    rank = objective(c=0.025, epsilon=1e-12, elites=3)
    rank(CostBatch(main, components={GUIDANCE: guidance}), 0)
    # The preliminary elites are samples 0, 1 and the diverged 2 (only two are finite); the ranges are over 0, 1.
    assert rank.records[-1].main_range == 2.0
    assert rank.records[-1].lambdas[GUIDANCE] == pytest.approx(0.025 * 2.0 / 2.0)


def test_weighted_auxiliary_cost_is_invariant_to_rescaling_it():
    rng = np.random.default_rng(1)
    main, guidance = rng.normal(0, 1, 30), rng.uniform(0, 2, 30)
    costs = []
    for scale in (1.0, 1e-3, 1e4):
        rank = objective(epsilon=1e-12, elites=10)
        costs.append(rank(CostBatch(main, components={GUIDANCE: scale * guidance}), 0))
    np.testing.assert_allclose(costs[1], costs[0], rtol=1e-8)
    np.testing.assert_allclose(costs[2], costs[0], rtol=1e-8)


def test_fixed_lambda_and_missing_components():
    main, guidance = np.array([1.0, 2.0, 3.0]), np.array([1.0, 0.0, 2.0])
    rank = objective(adaptive=False)
    np.testing.assert_array_equal(rank(CostBatch(main, components={GUIDANCE: guidance}), 0), main + 2.0 * guidance)
    np.testing.assert_array_equal(rank(CostBatch(main), 1), main)  # no guidance term: f = J


# --------------------------------------------------------- observations
@pytest.mark.parametrize(
    "task_name, tolerance",
    [
        ("point_reach", 1e-12),
        ("halfcheetah_running", 1e-12),
        ("door_sparse", 1e-12),
        ("relocate", 1e-12),
        ("fetch_pick_place_sparse", 1e-9),  # solver warm start of later steps (see BatchEvaluator)
        ("humanoid_standup", None),  # replay fallback; contact forces depend on the warm start
    ],
)
def test_observations_of_simulated_batches_equal_the_real_environments(task_name, tolerance, workers):
    worker = workers(task_name)
    task, env = worker.task, worker.env
    rng = np.random.default_rng(0)
    env.reset(seed=3)
    for _ in range(5):
        task.step_env(env, rng.uniform(-1, 1, task.action_dim))
    state = task.capture(env)
    actions = rng.uniform(-1, 1, (1, 8, task.action_dim))
    real = np.array([task.observe(task.step_env(env, a).observation) for a in actions[0]])

    batch = worker.evaluator.simulate(state, np.repeat(actions, 2, axis=0), keep_substeps=True)
    reader = ObservationReader(task, worker.scratch)
    replayed = reader.replay(worker.model, state, batch)
    if tolerance is None:
        assert not task.batch_observations
        np.testing.assert_allclose(replayed[0], real, rtol=1e-3, atol=1e-6)
        return
    assert task.batch_observations  # the vectorised path
    vectorised = reader.read(worker.model, state, batch)
    np.testing.assert_allclose(vectorised[0], real, rtol=0, atol=tolerance)
    np.testing.assert_allclose(vectorised[1], vectorised[0], rtol=0, atol=0)
    np.testing.assert_allclose(replayed, vectorised, rtol=0, atol=max(tolerance, 1e-9))


# -------------------------------------------------------------- iCEM_pi
def test_warm_start_is_the_policys_closed_loop_rollout_and_the_policy_sequence_is_proposed(workers, monkeypatch):
    worker = workers("point_reach")
    policy = random_policy(worker)
    state, observation = start(worker)
    expert = worker.expert(expert_settings("point_reach"), seed=4)
    expert.reset(4)

    # The policy's actions rolled out in a fresh real environment from the same state.
    env = make_task("point_reach").make_env()
    env.reset(seed=0)
    worker.task.restore(env, state)
    expected, current = [], observation
    for _ in range(expert.horizon):
        expected.append(policy(current))
        current = worker.task.observe(worker.task.step_env(env, expected[-1]).observation)
    env.close()

    seen = {}
    original = expert.planner.plan

    def plan(cost_function, proposals=None):
        seen["mean"] = expert.planner.memory.mean.copy()
        seen["proposals"] = proposals
        return original(cost_function, proposals)

    monkeypatch.setattr(expert.planner, "plan", plan)
    expert.act(state, observation, policy)
    np.testing.assert_allclose(seen["mean"], np.array(expected), atol=1e-12)  # mu_0 = pi's h-step rollout
    np.testing.assert_allclose(seen["proposals"][0], np.array(expected), atol=1e-12)
    expert.act(state, observation, policy)  # t = 1: the memory, not a new warm start
    assert not np.allclose(seen["mean"], np.array(expected))


def test_mean_and_policy_sequence_each_replace_one_sample_of_the_last_iteration(workers, monkeypatch):
    worker = workers("point_reach")
    policy = random_policy(worker)
    state, observation = start(worker)
    calls = {}
    for switch in (True, False):
        expert = worker.expert(expert_settings("point_reach", policy_samples=switch), seed=4)
        expert.reset(4)
        evaluated, means = [], []
        sample = expert.planner._sample
        monkeypatch.setattr(
            expert.planner, "_sample", lambda m, s, c, f=sample, seen=means: (seen.append(m.copy()), f(m, s, c))[1]
        )
        costs = expert._costs
        monkeypatch.setattr(expert, "_costs", lambda *a, f=costs, seen=evaluated: (seen.append(a[-1].copy()), f(*a))[1])
        info = expert.act(state, observation, policy)
        calls[switch] = (evaluated, means, info)
    evaluated, means, info = calls[True]
    sequence = expert.policy_rollout(state, observation, policy)
    last = evaluated[-1]
    assert [len(e) for e in evaluated] == [len(e) for e in calls[False][0]] == [25, 20]  # budget unchanged
    assert info.trajectories == calls[False][2].trajectories == 45
    np.testing.assert_array_equal(last[0], means[-1])  # the mean, in the last iteration only
    np.testing.assert_allclose(last[1], sequence, atol=1e-12)  # the policy's own sequence
    assert not any(np.allclose(e, sequence) for e in evaluated[0])
    assert not any(np.allclose(e, sequence) for e in calls[False][0][-1])


@pytest.mark.parametrize("policy_samples, rollouts", [(True, 3), (False, 1)])
def test_the_policy_is_rolled_out_only_when_its_sequence_is_used(workers, monkeypatch, policy_samples, rollouts):
    """Warm start needs the policy's sequence at t = 0 only; policy samples need it at every step."""
    worker = workers("point_reach")
    policy = random_policy(worker)
    state, observation = start(worker)
    expert = worker.expert(expert_settings("point_reach", policy_samples=policy_samples), seed=4)
    expert.reset(4)
    calls = []
    rollout = expert.policy_rollout
    monkeypatch.setattr(expert, "policy_rollout", lambda *a: (calls.append(1), rollout(*a))[1])
    for _ in range(3):
        expert.act(state, observation, policy)
    assert len(calls) == rollouts


def test_shift_initialisation_takes_the_policys_action_at_the_last_predicted_state(workers):
    worker = workers("point_reach")
    policy = random_policy(worker, seed=2)
    state, observation = start(worker)
    expert = worker.expert(expert_settings("point_reach"), seed=5)
    expert.reset(5)
    info = expert.act(state, observation, policy)

    env = make_task("point_reach").make_env()
    env.reset(seed=0)
    worker.task.restore(env, state)
    for action in info.plan:
        last = worker.task.observe(worker.task.step_env(env, action).observation)
    env.close()
    mean = expert.planner.memory.mean
    np.testing.assert_allclose(mean[-1], policy(last), atol=1e-9)
    np.testing.assert_array_equal(info.action, info.plan[0])
    assert np.all(np.abs(mean) <= 1)

    plain = worker.expert(expert_settings("point_reach", warm_start=False), seed=5)
    plain.reset(5)
    plain.act(state, observation, policy)
    np.testing.assert_array_equal(plain.planner.memory.mean[-1], plain.planner.memory.mean[-2])  # eq. 33: repeat


def test_adaptive_expert_executes_the_best_sequence_of_the_last_iteration(workers, monkeypatch):
    """f changes with lambda between CEM-iterations, so the planner's best-ever (compared across iterations)
    is not the executed sequence: the best of the last iteration (kept elites re-weighed) is."""
    worker = workers("point_reach")
    state, observation = start(worker)
    expert = worker.expert(expert_settings("point_reach"), seed=6)
    expert.reset(6)
    original = expert.planner.plan

    def plan(*args, **kwargs):
        result = original(*args, **kwargs)  # pretend an earlier iteration's f looked better
        stale = np.clip(result.plan + 0.5, -1, 1)
        return result._replace(plan=stale, action=stale[0])

    monkeypatch.setattr(expert.planner, "plan", plan)
    info = expert.act(state, observation, random_policy(worker))
    assert len(info.records) == 2 and all(GUIDANCE in r.lambdas for r in info.records)
    np.testing.assert_array_equal(info.plan, expert.planner.memory.elites[0])
    np.testing.assert_array_equal(info.action, expert.planner.memory.elites[0][0])


def test_relabeling_the_same_states_with_the_same_chunk_seed_gives_identical_labels(workers):
    worker = workers("point_reach")
    policy = random_policy(worker)
    weights = policy.weights
    episode = worker.policy_episode(7, 12, weights).trajectory
    tree, observations = episode.sim_states.to_tree(), episode.observations[:-1]
    settings = expert_settings("point_reach")
    first = worker.relabel(tree, observations, weights, 11, settings)
    again = RelabelWorker("point_reach").relabel(tree, observations, weights, 11, settings)  # another worker
    other = worker.relabel(tree, observations, weights, 12, settings)
    np.testing.assert_array_equal(first.actions, again.actions)
    np.testing.assert_array_equal(first.lambdas, again.lambdas)
    assert first.actions.shape == (12, 2) and not np.array_equal(first.actions, other.actions)
    assert derived_seed(0, 3, "relabel", 2) == derived_seed(0, 3, "relabel", 2) != derived_seed(0, 3, "relabel", 3)


@pytest.mark.parametrize("restart", ["state", "chunk"])
def test_relabeling_starts_alg_2_afresh_where_relabel_restart_says(restart, workers):
    """`state`: every label is what a fresh expert (t = 0, warm start from the policy at that state) gives
    there; `chunk`: only the first is, later states inherit the previous state's plan."""
    worker = workers("point_reach")
    policy = random_policy(worker)
    episode = worker.policy_episode(7, 5, policy.weights).trajectory
    states, observations = episode.sim_states, episode.observations[:-1]
    settings = expert_settings("point_reach", relabel_restart=restart)
    labels = worker.relabel(states.to_tree(), observations, policy.weights, 11, settings).actions
    fresh = []
    for k in range(len(labels)):
        expert = worker.expert(settings, seed=0)
        expert.reset(relabel_seed(11, k) if restart == "state" else 11)
        fresh.append(expert.act(states[k], observations[k], policy).action)
    same = [np.array_equal(label, alone) for label, alone in zip(labels, fresh)]
    assert same == ([True] * 5 if restart == "state" else [True, False, False, False, False])


@pytest.mark.parametrize("task_name", ["door_sparse", "fetch_pick_place_sparse"])
def test_recorded_states_carry_what_lives_outside_mjdata(task_name, workers):
    """Door's randomised door position and Fetch's goal and mocap: another worker, reset elsewhere, replays
    a recorded policy episode step for step from its recorded states."""
    worker = workers(task_name)
    policy = random_policy(worker)
    episode = worker.policy_episode(9, 6, policy.weights).trajectory
    other = RelabelWorker(task_name)
    try:
        other.env.reset(seed=123)  # a different door position / goal in the other worker's model
        for t in (0, 3):
            state = episode.sim_states[t]
            rewards = other.evaluator.rewards(state, episode.actions[None, t:])
            np.testing.assert_allclose(rewards[0], episode.rewards[t:], atol=1e-9)
    finally:
        other.close()


def test_fig_11_lambda_stays_zero_until_an_elite_moves_the_box(workers):
    """Fetch, untrained policy: J (a function of the box position only) is exactly equal for every
    preliminary elite until one of them moves the box; until then lambda is exactly 0."""
    worker = workers("fetch_pick_place_sparse")
    policy = random_policy(worker)
    # At h = 30 the first step's samples can already reach the box; at h = 20 the first plans of this start
    # leave it untouched, as in Fig. 11's first steps.
    expert = worker.expert(expert_settings("fetch_pick_place_sparse", horizon=20), seed=0)
    task, env = worker.task, worker.env
    observation, _ = env.reset(seed=0)
    current = task.observe(observation)
    expert.reset(0)
    records = []
    for _ in range(10):
        info = expert.act(task.capture(env), current, policy)
        records += info.records
        if info.records[-1].main_range > 0:
            break
        current = task.observe(task.step_env(env, info.action).observation)
    flat = [r for r in records if r.main_range == 0]
    assert flat and records[0].main_range == 0  # nothing moves the box at first
    assert all(r.lambdas[GUIDANCE] == 0.0 for r in flat)
    assert records[-1].main_range > 0 and records[-1].lambdas[GUIDANCE] > 0  # an elite moved it


# -------------------------------------------------------------- policy
def test_policy_training_fits_and_weights_round_trip_without_pickle(tmp_path):
    rng = np.random.default_rng(0)
    # One constant feature, and one far from zero with a small spread, where a mean stored in float32 is off by
    # up to 0.003 standard deviations: the stored standardisation must be the one trained with.
    observations = rng.normal(size=(300, 5)) * [1, 10, 0.1, 0.01, 0] + [0, 0, 0, 1000.3, 0]
    actions = np.clip(np.tanh(observations[:, :2] @ np.array([[1.0, -0.5], [0.05, 0.1]])), -1, 1)
    trainer = PolicyTrainer(0, {"gradient_steps": 150, "batch_size": 64}, task="point_reach", obs_dim=5, action_dim=2)
    untrained = trainer.weights()
    report = trainer.train({"observations": observations, "actions": actions})
    assert report.weights.version == 1 and untrained.version == 0 and report.threads == 1
    assert report.loss < 0.5 * np.mean(actions**2) and report.last_loss < report.first_loss

    path = tmp_path / "policy.npz"
    path.write_bytes(report.weights.to_bytes())
    policy = load_policy(path)  # the documented one-liner
    with np.load(path, allow_pickle=False) as archive:  # plain numpy reads it too
        assert "arrays/w0" in archive.files
    import torch

    with torch.no_grad():
        expected = trainer.model(trainer._inputs(observations)).numpy()
    np.testing.assert_allclose(policy.raw(observations), expected, atol=1e-5)
    assert np.all(np.abs(policy(observations * 100)) <= 1)
    assert policy.task == "point_reach" and PolicyWeights.from_bytes(path.read_bytes()).version == 1
    with pytest.raises(checkpoint.CheckpointError):
        PolicyWeights.from_bytes(checkpoint.to_bytes({"format": "something else"}))


@pytest.mark.parametrize("reinitialize", [False, True])
def test_a_training_continues_from_the_last_unless_reinitialize_says(reinitialize):
    rng = np.random.default_rng(1)
    observations = rng.normal(size=(400, 4))
    dataset = {"observations": observations, "actions": np.tanh(observations[:, :2] * [1.0, -0.5])}
    settings = {"gradient_steps": 300, "batch_size": 64, "reinitialize": reinitialize}
    trainer = PolicyTrainer(3, settings, task="point_reach", obs_dim=4, action_dim=2)
    first, second = trainer.train(dataset), trainer.train(dataset)
    # Continuing, the second training's first batch is as well fitted as the end of the first; afresh it is
    # as badly fitted as the first training's first batch was.
    if reinitialize:
        assert second.first_loss > 0.5 * first.first_loss > 2 * first.last_loss
    else:
        assert second.first_loss < 1.5 * first.last_loss < 0.5 * first.first_loss
    assert second.weights.version == 2
    again = PolicyTrainer(3, settings, task="point_reach", obs_dim=4, action_dim=2)
    again.train(dataset)
    np.testing.assert_array_equal(again.train(dataset).weights.arrays["w0"], second.weights.arrays["w0"])


@pytest.mark.parametrize("keep_function", [True, False])
def test_a_new_standardisation_keeps_what_the_carried_over_network_computes(keep_function, monkeypatch):
    """The window moves (other mean and scale): with keep_function the trained network's output for every raw
    observation is the same right after the refit, before any gradient step; without it, it is not."""
    import torch

    rng = np.random.default_rng(4)
    observations = rng.normal(size=(400, 4))
    actions = np.tanh(observations[:, :2] * [1.0, -0.5])
    settings = {"gradient_steps": 200, "batch_size": 64, "keep_function": keep_function}
    trainer = PolicyTrainer(3, settings, task="point_reach", obs_dim=4, action_dim=2)
    trained = Policy(trainer.train({"observations": observations, "actions": actions}).weights)
    probe = rng.normal(size=(50, 4)) * 2  # standardised either way, all well inside +-INPUT_CLIP
    moved = observations * [3.0, 1.5, 1.0, 2.0] + [5.0, -2.0, 0.0, 1.0]
    refitted = {}

    def output_before_the_first_step():
        with torch.no_grad():
            refitted.setdefault("raw", trainer.model(trainer._inputs(probe)).numpy())

    monkeypatch.setattr(trainer.optimiser, "step", output_before_the_first_step)
    trainer.train({"observations": moved, "actions": actions}, steps=1)
    assert not np.allclose(trainer.mean, 0, atol=1)  # the standardisation did move
    assert np.allclose(refitted["raw"], trained.raw(probe), atol=1e-4) == keep_function


@pytest.mark.parametrize("carry_moments", [True, False])
def test_a_rescaled_standardisation_carries_adams_moments_into_the_new_coordinates(carry_moments, monkeypatch):
    """The spread of the inputs doubles: the folded first layer's gradient halves, and Adam's moments scale with it,
    so they stand to the gradients they will meet as they stood to the old ones; left alone, they do not."""
    import torch

    import workers.policy.training as training

    if not carry_moments:
        monkeypatch.setattr(training, "rescale_inputs_of", lambda weight, scale, optimiser: weight.data.mul_(scale))
    rng = np.random.default_rng(5)
    observations = rng.normal(size=(400, 4)) + [1.0, -1.0, 0.0, 2.0]
    actions = np.tanh(observations[:, :2] * [0.7, -0.4])
    trainer = PolicyTrainer(3, {"gradient_steps": 50, "batch_size": 64}, obs_dim=4, action_dim=2)
    trainer.train({"observations": observations, "actions": actions})
    first = trainer.linears[0]
    target = torch.as_tensor(actions, dtype=torch.float32)

    def gradient_and_moments():
        trainer.model.zero_grad()
        torch.mean((trainer.model(trainer._inputs(observations)) - target) ** 2).backward()
        state = trainer.optimiser.state[first.weight]
        return first.weight.grad.clone(), state["exp_avg"].clone(), state["exp_avg_sq"].clone()

    gradient, first_moment, second_moment = gradient_and_moments()
    scale = np.array([2.0, 1.0, 1.0, 2.0])
    trainer._restandardise_first_layer(trainer.mean, trainer.std * scale)
    trainer.std = trainer.std * scale
    new_gradient, new_first_moment, new_second_moment = gradient_and_moments()
    torch.testing.assert_close(new_gradient, gradient / torch.as_tensor(scale, dtype=torch.float32))
    carried = torch.allclose(new_first_moment / new_gradient, first_moment / gradient, rtol=1e-4)
    assert carried == carry_moments
    assert torch.allclose(new_second_moment / new_gradient**2, second_moment / gradient**2, rtol=1e-4) == carried


def test_restoring_a_trainer_to_before_its_first_training_forgets_the_training():
    """A round 0 re-run after a restore gets the random initialisation again, not the weights trained since."""
    rng = np.random.default_rng(2)
    dataset = {"observations": rng.normal(size=(200, 4)), "actions": rng.uniform(-1, 1, size=(200, 2))}
    settings = {"gradient_steps": 20, "batch_size": 32}
    trainer = PolicyTrainer(5, settings, task="point_reach")
    empty = trainer.state_dict()
    trainer.train(dataset)
    trainer.load_state_dict(empty)
    restored, fresh = trainer.initialize(4, 2), PolicyTrainer(5, settings, task="point_reach").initialize(4, 2)
    assert restored.version == fresh.version == 0
    np.testing.assert_array_equal(restored.arrays["w0"], fresh.arrays["w0"])
    retrained, uninterrupted = trainer.train(dataset), PolicyTrainer(5, settings).train(dataset)
    np.testing.assert_array_equal(retrained.weights.arrays["w0"], uninterrupted.weights.arrays["w0"])


def test_trainer_threads_follow_its_cpus():
    assert PolicyTrainer(0, cpus=0.5).threads == 1 and PolicyTrainer(0, cpus=2).threads == 2
    roles = {r.name: r for r in ApexProgram.roles_for(trial(), 1, {"relabel": 3})}
    assert roles["relabel"].count == 3 and not roles["relabel"].stateful
    # The trainer reserves nothing of its own and trains with the threads of the relabel worker it waits for.
    assert roles["trainer"].stateful and roles["trainer"].cpus == 0 and roles["trainer"].kwargs["cpus"] == 1


# ------------------------------------------------------------- program
def trial(seed: int = 0, **overrides) -> TrialSpec:
    settings = (
        dict(
            planner={"budget": 45, "horizon": 8},
            iterations=3,
            rollouts=2,
            window=3,
            episode_steps=10,
            relabel_chunk=4,
            policy={"gradient_steps": 20, "batch_size": 64},
        )
        | overrides
    )
    resolved = ApexProgram.resolve(ApexSettings(**settings), make_task("point_reach"))
    return TrialSpec("apex", "point_reach", resolved, seed)


COMPARED = ("expert_return", "policy_return", "loss/first_training", "loss/second_training", "lambda/relabel_mean",
            "lambda/expert_mean", "dataset/steps", "weights_version")  # fmt: skip


@pytest.mark.parametrize(
    "window_counts, window, rollouts",
    [
        ("iterations", 2, [4, 8, 8]),  # W x n = 2 x 2 expert rollouts and their 4 relabeled episodes
        ("episodes", 3, [4, 6, 6]),  # W x n = 3 x 2 episodes of either kind
    ],
)
def test_iterations_report_every_phase_and_keep_the_window(window_counts, window, rollouts):
    reports = run_locally(ApexProgram, trial(window=window, window_counts=window_counts))
    assert [r.step for r in reports] == [0, 1, 2] and reports[-1].done
    for index, report in enumerate(reports):
        m = report.metrics
        assert m["weights_version"] == 2 * (index + 1) and m["weights_version/expert"] == 2 * index
        assert m["weights_version/relabel"] == m["weights_version/policy"] == 2 * index + 1
        assert m["dataset/relabeled_steps"] == 20  # every state of the 2 policy episodes, once
        assert m["expert_trajectories_per_step"] == pytest.approx((45 + 9 * 48) / 10)
        for phase in ("expert", "relabel"):
            assert 0 <= m[f"lambda/{phase}_zero_fraction"] <= 1 and m[f"lambda/{phase}_max"] >= 0
        assert {"seconds/expert", "seconds/dagger", "seconds/training", "seconds/iteration", "core_minutes"} <= set(m)
        assert "seconds/evaluation" not in m  # this trial does not evaluate
        assert {a.path for a in report.artifacts} == {f"policy/policy_{index:04d}.npz", "apex_curves.png"}
    # Rollouts of 10 steps, 2 expert and 2 relabeled per iteration; the oldest leave.
    assert [r.metrics["dataset/rollouts"] for r in reports] == rollouts
    assert [r.metrics["dataset/steps"] for r in reports] == [10 * n for n in rollouts]
    weights = PolicyWeights.from_bytes(reports[-1].artifacts[0].data)
    assert weights.version == 6 and weights.task == "point_reach"
    summary = reports[-1].summary
    assert summary["final_policy_return"] == pytest.approx(np.mean([r.metrics["policy_return"] for r in reports]))


def test_a_success_summary_carries_the_episodes_behind_it():
    """Reports test a success figure as a rate of episodes: the last 5 iterations' policy rollouts (2 each, new
    seeds every iteration), and the evaluations' 3 episodes, which start alike at every evaluation: averaged over
    the three that fall in the last 5 iterations they are 3 distinct episodes, not 9."""
    spec = trial(evaluation_episodes=3, evaluate_every=2)
    roles = {s.name: LocalRoleGroup.build(s) for s in ApexProgram.roles_for(spec, 1, {})}
    program = ApexProgram(spec, roles, 1)
    nan = math.nan
    program.history = {
        "policy_success": [0.0, 0.5, 0.5, 1.0, 0.5, 1.0, 0.0],
        "evaluation_success": [nan, 1 / 3, nan, 2 / 3, nan, 1.0, 1.0],
    }
    summary = program._summary()
    assert summary["final_policy_success_episodes"] == 10 and summary["final_evaluation_success_episodes"] == 3
    assert summary["final_evaluation_success"] == pytest.approx(8 / 9)


def test_an_evaluation_is_timed_apart_from_table_12s_phases(monkeypatch):
    """Table 12's Total is expert + DAgger + training: an evaluation's time and CPU are logged on their own and
    stay out of seconds/iteration and core_minutes. Evaluation episodes are made to report a minute of CPU each."""
    from workers.methods.apex import derived_seed
    from workers.policy.worker import RelabelWorker

    spec = trial(iterations=1, evaluation_episodes=3)
    evaluation_seeds = {derived_seed(spec.seed, 0, "evaluation", k) for k in range(3)}
    episode = RelabelWorker.policy_episode

    def minute_long_evaluations(self, seed, steps, weights):
        result = episode(self, seed, steps, weights)
        return result._replace(cpu_seconds=60.0) if seed in evaluation_seeds else result

    monkeypatch.setattr(RelabelWorker, "policy_episode", minute_long_evaluations)
    (report,) = run_locally(ApexProgram, spec)
    m = report.metrics
    assert m["core_minutes/evaluation"] == 3.0 and m["core_minutes"] < 1.0
    assert m["seconds/evaluation"] > 0 and "evaluation_return" in m


def test_without_dagger_the_window_holds_w_times_n_expert_rollouts_either_way():
    """BC adds only expert rollouts, so it holds half of DAgger's data when the window counts iterations."""
    capacities = {
        (dagger, counts): ApexProgram.window_capacity(trial(window=5, dagger=dagger, window_counts=counts).settings)
        for dagger in (True, False)
        for counts in ("iterations", "episodes")
    }
    assert capacities == {(True, "iterations"): 20, (True, "episodes"): 10, (False, "iterations"): 10,
                          (False, "episodes"): 10}  # fmt: skip


def test_relabeled_episodes_hold_the_experts_labels_at_the_policys_states():
    spec = trial(iterations=1)
    calls: dict[str, list] = {}

    class Spy(LocalRoleGroup):
        def map(self, method, arguments):
            results = super().map(method, arguments)
            calls.setdefault(method, []).append((arguments, results))
            return results

    roles = {
        s.name: (Spy if s.name == "relabel" else LocalRoleGroup).build(s) for s in ApexProgram.roles_for(spec, 1, {})
    }
    program = ApexProgram(spec, roles, 1)
    program.run_round(0)
    ((_, policy_episodes),) = calls["policy_episode"]
    ((chunk_calls, chunks),) = calls["relabel"]
    assert [len(c[1]) for c in chunk_calls] == [4, 4, 2, 4, 4, 2]  # 10 states per episode in chunks of 4
    assert len({c[3] for c in chunk_calls}) == 6  # a seed per chunk
    relabeled = list(program.buffer.episodes)[2:]  # after the 2 expert episodes
    labels = np.concatenate([c.actions for c in chunks])
    np.testing.assert_array_equal(np.concatenate([e.actions for e in relabeled]), labels)
    for episode, rollout in zip(relabeled, policy_episodes):
        np.testing.assert_array_equal(episode.observations, rollout.trajectory.observations)
        assert not np.array_equal(episode.actions, rollout.trajectory.actions)  # the expert's, not the policy's
    for (tree, observations, *_), index, offset in zip(chunk_calls, [0, 0, 0, 1, 1, 1], [0, 4, 8] * 2):
        trajectory = policy_episodes[index].trajectory
        np.testing.assert_array_equal(tree["goal"], trajectory.sim_states.goal)  # what lives outside MjData
        np.testing.assert_array_equal(
            tree["physics"], trajectory.sim_states.physics[offset : offset + len(observations)]
        )
        np.testing.assert_array_equal(observations, trajectory.observations[offset : offset + len(observations)])
    program.close()


def test_variants_switch_the_phases():
    bc = run_locally(
        ApexProgram, trial(iterations=1, dagger=False, guidance=False, warm_start=False, policy_samples=False)
    )
    m = bc[0].metrics
    assert "dataset/relabeled_steps" not in m and "lambda/expert_mean" not in m
    assert m["dataset/steps"] == 20 and m["weights_version"] == 2  # trains twice on expert data only
    fixed = run_locally(ApexProgram, trial(iterations=1, adaptive_lambda=False, fixed_lambda=0.5))
    assert fixed[0].metrics["lambda/expert_mean"] == 0.5 and fixed[0].metrics["lambda/expert_zero_fraction"] == 0


def test_checkpoint_round_trip_continues_identically():
    spec = trial(seed=2)
    uninterrupted = run_locally(ApexProgram, spec)

    def fresh():
        roles = {s.name: LocalRoleGroup.build(s) for s in ApexProgram.roles_for(spec, 1, {})}
        return ApexProgram(spec, roles, 1)

    first = fresh()
    reports = [first.run_round(0), first.run_round(1)]
    data = checkpoint.to_bytes({"program": first.state_dict()})
    second = fresh()  # a new process: new trainer and workers
    second.load_state_dict(checkpoint.from_bytes(data)["program"])
    reports.append(second.run_round(2))
    for got, expected in zip(reports, uninterrupted):
        assert {k: got.metrics[k] for k in COMPARED} == {k: expected.metrics[k] for k in COMPARED}
    assert reports[-1].artifacts[0].data == uninterrupted[-1].artifacts[0].data  # the same weights
    assert reports[-1].summary == uninterrupted[-1].summary


def test_chapter_4_defaults_resolve_per_task():
    def resolved(task_name, **settings):
        return ApexProgram.resolve(ApexSettings(**settings), make_task(task_name))

    humanoid = resolved("humanoid_standup", planner={"budget": 45})
    assert (humanoid.rollouts, humanoid.window, humanoid.episode_steps) == (1, 100, 500)
    assert humanoid.planner.population_sizes() == [25, 20] and humanoid.planner.noise_beta == 2.0
    assert (resolved("fetch_pick_place_sparse").rollouts, resolved("fetch_pick_place_sparse").window) == (25, 150)
    assert (resolved("door_sparse").rollouts, resolved("door_sparse").episode_steps) == (10, 200)
    assert resolved("halfcheetah_running", rollouts=3).rollouts == 3
    assert METHODS["apex"] is ApexProgram


@pytest.mark.parametrize(
    "base, variant, expected",
    [
        ({"rollouts": 0}, None, (5, "base.rollouts", "greater than or equal to 1")),
        ({"window": 0}, None, (5, "base.window", "greater than or equal to 1")),
        ({"c": -0.1}, None, (5, "base.c", "greater than or equal to 0")),
        ({"warmstart": False}, None, (5, "base.warmstart", "unknown key (did you mean 'warm_start'?)")),
        ({}, {"name": "x", "no_dagger": True}, (8, "no_dagger", "unknown parameter path 'no_dagger'")),
    ],
)
def test_bad_settings_are_located_errors(base, variant, expected, tmp_path):
    import yaml

    sweep = {"name": "bad", "task": "point_reach", "method": "apex", "base": base or {"iterations": 1}}
    if variant:
        sweep["variants"] = [variant]
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump(sweep, sort_keys=False))
    with pytest.raises(SweepError) as error:
        load_sweep(path)
    (problem,) = error.value.problems
    line, where, message = expected
    assert (problem.line, problem.path) == (line, where) and message in problem.message


def test_shipped_apex_sweeps_resolve_as_published():
    halfcheetah = load_sweep(ROOT / "sweeps" / "paper" / "apex_halfcheetah.yaml")
    variants = {t.variant for t in halfcheetah.trials}
    assert variants == {
        "apex", "icem-bc", "icem-dagger", "icem-pi-gps", "apex-no-dagger", "apex-no-warm-start",
        "apex-no-policy-samples", "apex-fixed-lambda",
    }  # fmt: skip
    assert len({t.config.seed for t in halfcheetah.trials}) >= 2
    # Fig. 13's baselines as section 4.4 defines them (switches: guidance, adaptive, warm, samples, dagger).
    switches = {
        t.variant: (s.guidance, s.adaptive_lambda, s.warm_start, s.policy_samples, s.dagger)
        for t in halfcheetah.trials
        for s in [t.config.settings]
    }
    assert switches["apex"] == (True, True, True, True, True)
    assert switches["icem-bc"] == (False, True, False, False, False)
    assert switches["icem-dagger"] == (False, True, False, False, True)
    assert switches["icem-pi-gps"] == (True, False, True, False, False)
    for loaded in (halfcheetah, load_sweep(ROOT / "sweeps" / "paper" / "apex_door_sparse.yaml")):
        for t in loaded.trials:
            settings = t.config.settings
            assert settings.planner.population_sizes() == [25, 20] and settings.planner.horizon == 30
            assert (
                settings.c == 0.025 and settings.policy.gradient_steps == 1000 and settings.policy.hidden == [128] * 3
            )
    door = load_sweep(ROOT / "sweeps" / "paper" / "apex_door_sparse.yaml").trials[0].config.settings
    assert door.rollouts == 2 and door.iterations == 20
    assert load_sweep(ROOT / "sweeps" / "paper" / "apex_fetch.yaml").trials[0].config.settings.rollouts == 5


# ---------------------------------------------------------------- CLI
def cli_env() -> dict:
    """Subprocesses import this checkout (an installed icemlab elsewhere would shadow it)."""
    tests = str(ROOT / "tests")
    return {"PYTHONPATH": os.pathsep.join([str(ROOT), tests, os.environ.get("PYTHONPATH", "")])}


def test_policy_command_rolls_a_checkpoint_and_refuses_another_tasks(tmp_path):
    reports = run_locally(ApexProgram, trial(iterations=1))
    path = tmp_path / "policy_0000.npz"
    path.write_bytes(reports[-1].artifacts[0].data)
    result = cli("policy", str(path), "--episodes", "2", "--steps", "10", cwd=tmp_path, env=cli_env())
    assert result.returncode == 0, result.stderr
    assert "point_reach: policy version 2, 2 episode(s) of 10 steps" in result.stdout and "mean return" in result.stdout
    wrong = cli("policy", str(path), "--task", "halfcheetah_running", cwd=tmp_path, env=cli_env())
    assert wrong.returncode == 2
    assert "a policy of task 'point_reach', not 'halfcheetah_running'" in wrong.stderr
    junk = tmp_path / "junk.npz"
    junk.write_bytes(b"not a checkpoint")
    refused = cli("policy", str(junk), cwd=tmp_path, env=cli_env())
    assert refused.returncode == 2 and "not an APEX policy checkpoint" in refused.stderr


@pytest.mark.parametrize("damage", ["no_bias", "bad_version", "unknown_task"])
def test_a_damaged_policy_checkpoint_is_refused_with_its_reason(damage, tmp_path):
    """A checkpoint archive that is well formed but lacks an array, carries a version that is no number, or names
    a task this icemlab does not have: one line saying so, not a KeyError or ValueError from inside the loader."""
    from workers.policy.evaluate import PolicyCheckpointError, read_checkpoint

    tree = PolicyTrainer(0, obs_dim=6, action_dim=2, task="point_reach").weights().to_tree()
    if damage == "no_bias":
        del tree["arrays"]["b1"]
    elif damage == "bad_version":
        tree["version"] = "x"
    else:
        tree["task"] = "point_reech"
    path = tmp_path / "policy.npz"
    path.write_bytes(checkpoint.to_bytes(tree))
    with pytest.raises(PolicyCheckpointError) as error:
        read_checkpoint(path, None)
    expected = "did you mean 'point_reach'" if damage == "unknown_task" else "not an APEX policy checkpoint"
    assert expected in str(error.value) and str(path) in str(error.value)


def test_a_policy_is_rolled_as_long_as_chapter_4s_episodes_by_default(tmp_path):
    """Humanoid standup: APEX trains and evaluates on 500 steps (section 4.4), not the environment's 1000."""
    from workers.policy.evaluate import roll_policy

    task = make_task("humanoid_standup")
    env = task.make_env()
    try:
        obs_dim = len(task.observe(env.reset(seed=0)[0]))
    finally:
        env.close()
    path = tmp_path / "policy.npz"
    path.write_bytes(PolicyTrainer(0, obs_dim=obs_dim, action_dim=task.action_dim, task=task.name).weights().to_bytes())
    assert roll_policy(path, None).steps == 500
    assert roll_policy(path, None, steps=7).steps == 7


def test_benchmark_functions_measure_through_role_groups():
    from workers.policy.benchmark import relabel_rates, relabel_workload, training_rates

    workload = relabel_workload("point_reach", states=6, chunk=3, horizon=5)
    groups = [LocalRoleGroup("relabel", [RelabelWorker("point_reach")]) for _ in range(2)]
    rates = relabel_rates(groups, workload)
    assert rates["workers"] == [1, 1] and rates["states"] == 6 and rates["chunks"] == 2
    assert all(rate > 0 for rate in rates["states_per_second"]) and rates["ratio_to_first"][0] == 1
    training = training_rates(6, 2, threads=(1, 2), steps=3, samples=200)
    assert training["threads"] == [1, 2] and all(rate > 0 for rate in training["steps_per_second"])


# ----------------------------------------------------------- Fig. 9
@pytest.mark.slow
def test_fig_9_guided_relabeling_has_at_most_0_6_of_plain_icems_action_spread():
    """Fetch: a policy trained from one expert rollout; 10 consecutive states of that rollout relabeled
    10 times by plain iCEM and by guided, warm-started iCEM_pi (budget 45). Thesis: std 0.30 vs 0.13."""
    worker = RelabelWorker("fetch_pick_place_sparse")
    task = worker.task
    settings = expert_settings("fetch_pick_place_sparse", horizon=30)
    plain = expert_settings(
        "fetch_pick_place_sparse", horizon=30, guidance=False, warm_start=False, policy_samples=False
    )
    untrained = random_policy(worker)
    episode = worker.expert_episode(0, task.episode_length, untrained.weights, plain).trajectory
    trainer = PolicyTrainer(0, task=task.name, obs_dim=episode.observations.shape[1], action_dim=task.action_dim)
    weights = trainer.train({"observations": episode.observations[:-1], "actions": episode.actions}).weights
    states = worker.policy_episode(0, 20, weights).trajectory  # the states the policy visits
    tree = {k: v[10:20] for k, v in states.sim_states.to_tree().items() if k not in ("model_params", "goal")}
    tree |= {"model_params": states.sim_states.model_params, "goal": states.sim_states.goal}
    observations = states.observations[10:20]
    spread = {}
    for name, expert in (("plain", plain), ("guided", settings)):
        labels = np.stack([worker.relabel(tree, observations, weights, seed, expert).actions for seed in range(10)])
        spread[name] = float(labels.std(axis=0).mean())
    print(f"action std over 10 relabelings: plain iCEM {spread['plain']:.3f}, guided iCEM_pi {spread['guided']:.3f}")
    assert spread["guided"] <= 0.6 * spread["plain"]
    worker.close()
