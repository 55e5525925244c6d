"""Neural all-pairs shortest path against its definitions (thesis chapter 6, appendix E)."""

from __future__ import annotations

import math
from collections import Counter

import numpy as np
import pytest
import torch
from pydantic import ValidationError

from workers.distance.buffer import EpisodeBuffer, Episodes
from workers.distance.config import (
    CountSettings,
    DistanceSettings,
    LearnerSettings,
    method_settings,
)
from workers.distance.counts import (
    CountMinSketch,
    CountModels,
    PairCounts,
    RandomProjectionHash,
    StateActionCounts,
    code_collision_probability,
    collision_radius,
)
from workers.distance.her import future_fraction, sample_her_transitions
from workers.distance.learners import GoalLearner, GoalPolicy, default_q_clip
from workers.distance.loop import LoopSettings, NeuralAPSP, collect_episodes
from workers.distance.losses import (
    count_uncertainty,
    merge_and_relax_rates,
    sample_temporal,
    sample_triangular,
    temporal_targets,
    triangular_targets,
)
from workers.distance.network import DistanceFunction
from workers.distance.rewards import DistanceReward, SparseReward
from workers.distance.state import State, load_state, save_state
from workers.distance.trainer import DistanceTrainer
from workers.tasks.maze_distance import MazeDistance


@pytest.fixture(autouse=True)
def one_thread():
    torch.set_num_threads(1)


def marked_episodes(count: int, horizon: int, first: int = 0, obs_dim: int = 4, seed: int = 0) -> Episodes:
    """Episodes whose achieved goal ag(s_t) = (episode number, t) names the step it came from."""
    rng = np.random.default_rng(seed)
    observations = rng.normal(size=(count, horizon + 1, obs_dim))
    observations[..., 0] = np.arange(first, first + count)[:, None]
    observations[..., 1] = np.arange(horizon + 1)[None, :]
    achieved = observations[..., :2].copy()
    return Episodes(
        observations=observations,
        actions=rng.uniform(-1, 1, (count, horizon, 2)),
        achieved_goals=achieved,
        goals=np.stack([np.arange(first, first + count) + 0.5, np.full(count, -1.0)], axis=1),
        successes=np.zeros((count, horizon)),
    )


def filled_buffer(episodes: Episodes) -> EpisodeBuffer:
    buffer = EpisodeBuffer(10_000, episodes.horizon, episodes.observations.shape[-1], 2, 2)
    buffer.add(episodes)
    return buffer


# ------------------------------------------------------------ count models
def test_sketch_never_undercounts_even_when_rows_collide():
    """Small moduli make some codes collide in every row; the minimum over rows still never undercounts."""
    rng = np.random.default_rng(0)
    codes = rng.integers(-50, 50, (3000, 4))
    codes[:300] = codes[0]  # one heavy code among many light ones
    sketch = CountMinSketch(4, np.random.default_rng(1), moduli=(4999, 5003, 5009))
    sketch.add(codes)
    truth = Counter(map(tuple, codes))
    distinct = np.array(list(truth))
    estimate = sketch.query(distinct)
    exact = np.array([truth[tuple(c)] for c in distinct])
    assert (estimate >= exact).all()
    assert (estimate > exact).any() and (estimate == exact).any()  # the regime collides, but not everywhere


def test_sketch_with_published_moduli_is_exact_at_this_load():
    """Six rows of ~1e6 cells: with a few thousand codes an overcount would need a collision in all six rows."""
    rng = np.random.default_rng(2)
    codes = rng.integers(-1000, 1000, (5000, 8))
    codes[2500:] = codes[:2500]  # every code twice
    sketch = CountMinSketch(8, np.random.default_rng(3))
    sketch.add(codes)
    assert (sketch.query(codes) == 2).all()
    assert (sketch.query(rng.integers(2000, 3000, (200, 8))) == 0).all()


def test_keys_separate_the_codes_the_thesis_weighting_merges():
    """Weighting component l by 2^l gives (2, 0) and (0, 1) one key in every row; universal keys separate them."""
    moduli = np.array([999931, 999953, 999959, 999961, 999979, 999983])
    thesis_key = lambda code: sum(c * 2**place for place, c in enumerate(code)) % moduli  # noqa: E731
    assert (thesis_key((2, 0)) == thesis_key((0, 1))).all()
    sketch = CountMinSketch(2, np.random.default_rng(0))
    sketch.add(np.array([[2, 0]] * 5))
    assert sketch.query(np.array([[2, 0], [0, 1]])).tolist() == [5, 0]


def test_collision_rate_follows_the_projection_geometry():
    """One code component of inputs r apart collides with probability E[max(0, 1 - r|Z|/sigma)] (App. E.1).

    4000 independent components (rows of M with their offsets) give the
    per-component rate; grouped by 8 they are 500 independent k = 8 hashes,
    whose whole-code rate is that probability to the 8th power.
    """
    rng = np.random.default_rng(0)
    sigma, dim = 2.0, 5
    projection = RandomProjectionHash(dim, 4000, sigma, rng)
    rates, groups = [], []
    for r in (0.1, 0.5, 1.0, 2.0, 4.0):
        x = rng.uniform(-20, 20, (40, dim))
        direction = rng.normal(size=(40, dim))
        y = x + r * direction / np.linalg.norm(direction, axis=1, keepdims=True)
        same = projection.codes(x) == projection.codes(y)  # (40, 4000)
        rate = same.mean()
        theory = code_collision_probability(r, sigma, 1)
        assert rate == pytest.approx(theory, abs=0.02), r
        whole = same.reshape(40, 500, 8).all(axis=2).mean()
        assert whole == pytest.approx(code_collision_probability(r, sigma, 8), abs=0.03), r
        rates.append(rate)
        groups.append(whole)
    assert rates == sorted(rates, reverse=True) and groups == sorted(groups, reverse=True)
    assert rates[0] > 0.95 and rates[-1] < 0.3


def test_collision_radius_of_the_table_20_hashes():
    """Whole codes collide half the time at ~sigma ln 2 / (0.8 k): fine for Fetch, coarse for Point Maze."""
    assert code_collision_probability(collision_radius(0.3, 128), 0.3, 128) == pytest.approx(0.5)
    assert collision_radius(0.3, 128) == pytest.approx(0.3 * np.log(2) / (np.sqrt(2 / np.pi) * 128), rel=0.01)
    assert collision_radius(20.0, 32) == pytest.approx(0.54, abs=0.01)


def test_pair_counts_equal_a_brute_force_count():
    """N(s, a, g') after one episode: every (s_i, a_i, ag(s_j)) with i < j <= T, counted once per pair."""
    horizon = 7
    episodes = marked_episodes(2, horizon, seed=3)
    # Coarse buckets so that many different pairs share a code and counts exceed 1.
    counts = PairCounts(4, 2, 2, key_dim=3, sigma=25.0, rng=np.random.default_rng(0))
    counts.add_episodes(episodes)
    brute: Counter = Counter()
    triples = []
    for e in range(len(episodes)):
        for i in range(horizon):
            for j in range(i + 1, horizon + 1):
                s, a, g = episodes.observations[e, i], episodes.actions[e, i], episodes.achieved_goals[e, j]
                code = tuple(counts.pair_codes(s[None], a[None], g[None])[0])
                brute[code] += 1
                triples.append((s, a, g))
    assert counts.sketch.total == len(episodes) * horizon * (horizon + 1) // 2 == sum(brute.values())
    assert max(brute.values()) > 1
    s, a, g = (np.array(column) for column in zip(*triples))
    expected = [brute[tuple(c)] for c in counts.pair_codes(s, a, g)]
    assert counts.query(s, a, g).tolist() == expected


def test_state_action_counts_every_step_once():
    episodes = marked_episodes(3, 5)
    counts = StateActionCounts(4, 2, key_dim=16, sigma=0.5, rng=np.random.default_rng(0))
    counts.add_episodes(episodes)
    counts.add_episodes(episodes.select(slice(0, 1)))
    obs, actions = episodes.observations[:, :-1], episodes.actions
    assert counts.sketch.total == 3 * 5 + 5
    assert counts.query(obs[0], actions[0]).tolist() == [2] * 5
    assert counts.query(obs[1:].reshape(-1, 4), actions[1:].reshape(-1, 2)).tolist() == [1] * 10
    assert counts.query(episodes.observations[:, -1], actions[:, 0]).tolist() == [0] * 3


def test_count_models_export_as_arrays():
    episodes = marked_episodes(2, 6)
    models = CountModels(CountSettings(single_key_dim=8, pair_key_dim=8, sigma=1.0), 4, 2, 2, seed=5)
    models.update(episodes)
    restored = CountModels(CountSettings(single_key_dim=8, pair_key_dim=8, sigma=1.0), 4, 2, 2, seed=99)
    restored.load(models.state())
    s, a, g = episodes.observations[0, :-1], episodes.actions[0], episodes.achieved_goals[0, 1:]
    assert restored.pair.query(s, a, g).tolist() == models.pair.query(s, a, g).tolist() != [0] * 6
    assert restored.single.query(s, a).tolist() == models.single.query(s, a).tolist() == [1] * 6
    assert all(isinstance(v, np.ndarray) and v.dtype != object for v in models.state().arrays.values())


# ------------------------------------------------------------- temporal loss
def test_temporal_pairs_come_from_one_episode_with_j_after_i():
    episodes = marked_episodes(3, 6)
    batch = sample_temporal(filled_buffer(episodes), 4000, np.random.default_rng(0))
    assert (batch.first >= 0).all() and (batch.first <= 5).all()
    assert (batch.second > batch.first).all() and (batch.second <= 6).all()
    assert np.array_equal(batch.goals[:, 0], batch.episodes)  # ag(s_j) of the same episode
    assert np.array_equal(batch.goals[:, 1], batch.second)
    assert np.array_equal(batch.observations[:, 1], batch.first)
    assert np.array_equal(batch.steps, batch.second - batch.first)
    assert len(set(zip(batch.first, batch.second))) == 6 * 7 // 2  # every pair i < j <= T occurs
    ddl = sample_temporal(filled_buffer(episodes), 4000, np.random.default_rng(0), min_gap=0)
    assert (ddl.second >= ddl.first).all() and (ddl.steps == 0).any()


def test_temporal_labels_take_the_network_only_where_counts_back_it():
    """min(j - i, d_old + C / (1 + N)^M) with C = 400, M = 2 (eq. 29, 31a)."""
    assert count_uncertainty(np.array([0, 1, 3, 19])).tolist() == [400.0, 100.0, 25.0, 1.0]
    steps = np.array([10.0, 10.0, 10.0, 3.0])
    d_old = np.array([2.0, 2.0, 2.0, 2.0])
    targets = temporal_targets(steps, d_old, count_uncertainty(np.array([0, 3, 19, 19])))
    assert targets.tolist() == [10.0, 10.0, 3.0, 3.0]


def test_temporal_phase_bootstraps_once_counts_accumulate():
    """A trainer whose (s, a) were counted many times uses d_old + U below j - i for long pairs."""
    episodes = marked_episodes(2, 20)
    settings = DistanceSettings(hidden=(16,), batch_size=64, temporal_updates_per_episode=2, triangular=False)
    counts = CountSettings(single_key_dim=4, pair_key_dim=4, sigma=1000.0)  # one bucket: N grows with every step
    trainer = DistanceTrainer(settings, counts, 4, 2, 2, horizon=20, seed=0)
    trainer.add_episodes(episodes)
    assert trainer.train()["distance/bootstrapped_fraction"] > 0.3
    fresh = DistanceTrainer(settings, counts.model_copy(update=dict(sigma=1e-6)), 4, 2, 2, horizon=20, seed=0)
    fresh.add_episodes(episodes)  # every (s, a) in its own bucket: N = 1, U = 100 > j - i
    assert fresh.train()["distance/bootstrapped_fraction"] == 0.0


def test_target_is_copied_after_the_temporal_phase():
    """d_old stays frozen during the temporal updates and equals d_theta right after them (Alg. 4 line 10)."""
    settings = DistanceSettings(hidden=(16,), batch_size=32, temporal_updates_per_episode=3, triangular=False)
    trainer = DistanceTrainer(settings, CountSettings(single_key_dim=4, pair_key_dim=4, sigma=1.0), 4, 2, 2, 6)
    initial = [p.detach().clone() for p in trainer.model.target.net.parameters()]
    trainer.add_episodes(marked_episodes(2, 6))
    trainer.temporal_step()
    assert all(torch.equal(a, b) for a, b in zip(initial, trainer.model.target.net.parameters()))
    trainer.train()
    online, target = trainer.model.function.net.parameters(), trainer.model.target.net.parameters()
    assert all(torch.equal(a, b) for a, b in zip(online, target))
    assert not all(torch.equal(a, b) for a, b in zip(initial, trainer.model.target.net.parameters()))


def test_target_keeps_the_input_statistics_it_was_copied_with():
    """Merging new episodes moves the live normalisation; d_old, a frozen function, must not move with it."""
    settings = DistanceSettings(hidden=(16,), batch_size=32, temporal_updates_per_episode=2, triangular=False)
    trainer = DistanceTrainer(settings, CountSettings(single_key_dim=4, pair_key_dim=4, sigma=1.0), 4, 2, 2, 6)
    trainer.add_episodes(marked_episodes(2, 6))
    trainer.train()
    probe = marked_episodes(1, 6, seed=5)
    observations, actions, goals = probe.observations[0, :6], probe.actions[0], probe.achieved_goals[0, 1:]
    before_target = trainer.model.predict_target(observations, actions, goals)
    before_online = trainer.model.function(observations, actions, goals)
    far = marked_episodes(2, 6, first=40, seed=7)
    far.observations[:] *= 10.0
    trainer.add_episodes(far)  # new statistics, no training yet
    assert np.array_equal(trainer.model.predict_target(observations, actions, goals), before_target)
    assert not np.allclose(trainer.model.function(observations, actions, goals), before_online)


def test_a_checkpoint_without_the_targets_statistics_loads_them_from_the_live_function():
    """Checkpoints written before d_old kept its own statistics hold the target network alone."""
    settings = DistanceSettings(hidden=(16,), batch_size=32, temporal_updates_per_episode=2, triangular=False)
    counts = CountSettings(single_key_dim=4, pair_key_dim=4, sigma=1.0)
    trainer = DistanceTrainer(settings, counts, 4, 2, 2, 6)
    trainer.add_episodes(marked_episodes(2, 6))
    trainer.train()
    with torch.no_grad():  # d_old apart from d_theta, so a fallback that copied d_theta whole would show
        trainer.model.target.net[-1].bias.add_(0.5)
    state = trainer.model.state()
    old_arrays = {k: v for k, v in state.arrays.items() if not k.startswith("target/")}
    old_arrays |= {f"target/{k[len('target/net/'):]}": v for k, v in state.arrays.items() if k.startswith("target/net/")}
    old_meta = {k: v for k, v in state.meta.items() if k != "target"}
    restored = DistanceTrainer(settings, counts, 4, 2, 2, 6, seed=1)
    restored.model.load(State(old_arrays, old_meta))
    probe = marked_episodes(1, 6, seed=5)
    inputs = probe.observations[0, :6], probe.actions[0], probe.achieved_goals[0, 1:]
    assert np.array_equal(restored.model.predict_target(*inputs), trainer.model.predict_target(*inputs))
    assert not np.allclose(restored.model.predict_target(*inputs), restored.model.function(*inputs))


# ------------------------------------------------------------ triangular loss
def test_triangular_samples_draw_i_from_recent_episodes_and_j_from_all():
    old, recent = marked_episodes(3, 5, first=0), marked_episodes(2, 5, first=10)
    buffer = filled_buffer(old)
    buffer.add(recent)
    batch = sample_triangular(recent, buffer, 3000, np.random.default_rng(0))
    assert set(batch.observations[:, 0]) == {10, 11}
    assert np.array_equal(batch.goals[:, 0], batch.observations[:, 0] + 0.5)  # the desired goal of s_i's episode
    assert set(batch.via_observations[:, 0]) == {0, 1, 2, 10, 11}
    assert np.array_equal(batch.via_goals, batch.via_observations[:, :2])  # ag(s_j)


def test_triangular_labels_and_mask_on_hand_built_episodes():
    """Episode A never reached g, episode B did: only (s_i in A, s_j in B) triples train, to d_ij + d_jg."""
    horizon = 6
    a = marked_episodes(1, horizon, first=0, seed=1)
    b = marked_episodes(1, horizon, first=1, seed=2)
    goal = np.array([50.0, 50.0])
    b.achieved_goals[0, -1] = goal  # B ends at the goal
    counts = PairCounts(4, 2, 2, key_dim=16, sigma=0.1, rng=np.random.default_rng(0))
    counts.add_episodes(Episodes.concatenate([a, b]))
    s_i, a_i = a.observations[0, :horizon], a.actions[0]
    s_j, a_j = b.observations[0, :horizon], b.actions[0]
    to_goal = counts.query(s_i, a_i, np.tile(goal, (horizon, 1)))
    via_to_goal = counts.query(s_j, a_j, np.tile(goal, (horizon, 1)))
    assert (to_goal == 0).all() and (via_to_goal == 1).all()
    first_leg, second_leg = np.arange(horizon, dtype=float), np.full(horizon, 10.0)
    targets, mask = triangular_targets(first_leg, second_leg, to_goal, via_to_goal)
    assert mask.all() and targets.tolist() == (first_leg + 10).tolist()
    # s_j from A itself cannot lead to g: masked out.
    _, mask = triangular_targets(first_leg, second_leg, to_goal, to_goal)
    assert not mask.any()
    # s_i from B already reached g: masked out.
    _, mask = triangular_targets(first_leg, second_leg, via_to_goal, via_to_goal)
    assert not mask.any()


def test_triangular_targets_are_clipped_into_the_cap():
    first_leg, second_leg = np.array([-30.0, 20.0, 70.0, 400.0]), np.array([10.0, 30.0, 60.0, 500.0])
    counts = np.zeros(4)
    uncapped, _ = triangular_targets(first_leg, second_leg, counts, counts + 1)
    assert uncapped.tolist() == [-20.0, 50.0, 130.0, 900.0]
    capped, mask = triangular_targets(first_leg, second_leg, counts, counts + 1, cap=100.0)
    assert capped.tolist() == [0.0, 50.0, 100.0, 100.0] and mask.all()


def test_trainer_applies_the_triangular_cap():
    """The trainer's triangular phase fits targets clipped at the configured cap (eq. 31b with a bound)."""
    horizon = 8
    episodes = marked_episodes(2, horizon)
    # Each episode's desired goal is where the other one ended: s_i from one, s_j from the other pass the mask.
    episodes.goals[:] = episodes.achieved_goals[::-1, -1]
    settings = DistanceSettings(
        hidden=(16,),
        batch_size=64,
        temporal_updates_per_episode=0,
        triangular_updates_per_episode=1,
        triangular_target_cap=3.0,
    )
    trainer = DistanceTrainer(settings, CountSettings(single_key_dim=8, pair_key_dim=8, sigma=0.01), 4, 2, 2, horizon)
    trainer.add_episodes(episodes)
    fitted: list[np.ndarray] = []
    fit = trainer.model.fit

    def recording_fit(observations, actions, goals, targets, mask=None):
        fitted.append(np.asarray(targets)[np.asarray(mask, dtype=bool)])
        return fit(observations, actions, goals, targets, mask)

    trainer.model.fit = recording_fit  # type: ignore[method-assign]
    with torch.no_grad():  # every estimate far above the cap: 1000 steps
        trainer.model.target.net[-1].bias.fill_(1000.0)
    trainer.triangular_step()
    assert fitted and fitted[0].size > 0 and (fitted[0] == 3.0).all()


def test_merge_and_relax_rates_count_over_the_whole_batch():
    predictions = np.array([1.0, 5.0, 3.0, 2.0, 7.0])
    targets = np.array([4.0, 2.0, 3.0, 9.0, 8.0])
    mask = np.array([True, True, True, False, True])
    assert merge_and_relax_rates(predictions, targets, mask) == (2 / 5, 1 / 5)


def test_triangular_phase_only_trains_masked_samples():
    """With no pair counts at all (no goal ever reached) the triangular loss leaves the network untouched."""
    episodes = marked_episodes(2, 8)
    settings = DistanceSettings(
        hidden=(16,), batch_size=32, temporal_updates_per_episode=0, triangular_updates_per_episode=3
    )
    trainer = DistanceTrainer(settings, CountSettings(single_key_dim=8, pair_key_dim=8, sigma=0.01), 4, 2, 2, 8)
    trainer.add_episodes(episodes)
    before = {k: v.copy() for k, v in trainer.reward_weights().arrays.items() if k.startswith("net/")}
    metrics = trainer.train()
    assert metrics["distance/triangular_masked_fraction"] == 0.0
    # Nothing trained: no loss to report (not a perfect fit of 0), and every update was idle.
    assert math.isnan(metrics["distance/triangular_loss"]) and metrics["distance/triangular_idle_fraction"] == 1.0
    after = trainer.reward_weights().arrays
    assert all(np.array_equal(before[k], after[k]) for k in before)


def test_the_triangular_loss_is_that_of_the_samples_that_trained():
    """Updates no sample passed are left out of the loss, not averaged in as zeros; the rest weigh by how many of
    their samples trained."""
    trainer = DistanceTrainer(DistanceSettings(hidden=(16,), batch_size=32, temporal_updates_per_episode=0,
                                               triangular_updates_per_episode=4),
                              CountSettings(single_key_dim=8, pair_key_dim=8, sigma=0.01), 4, 2, 2, 8)  # fmt: skip
    trainer.add_episodes(marked_episodes(1, 8))
    steps = iter([{"loss": 2.0, "masked_fraction": 0.5}, {"loss": 0.0, "masked_fraction": 0.0},
                  {"loss": 5.0, "masked_fraction": 0.25}, {"loss": 0.0, "masked_fraction": 0.0}])  # fmt: skip
    trainer.triangular_step = lambda: next(steps)
    metrics = trainer.train()
    assert metrics["distance/triangular_loss"] == pytest.approx((2.0 * 0.5 + 5.0 * 0.25) / 0.75)
    assert metrics["distance/triangular_idle_fraction"] == 0.5


# ---------------------------------------------------------------------- HER
@pytest.mark.parametrize("k, fraction", [(0.0, 0.0), (0.25, 0.2), (4.0, 0.8)])
def test_her_relabels_future_goals_with_fraction_k_over_one_plus_k(k, fraction):
    """k = 0.25 relabels 20 % (App. E.3.1), k = 4 relabels 80 %; goals come from t + 1 ... T of the same episode."""
    episodes = marked_episodes(4, 10)
    batch = sample_her_transitions(filled_buffer(episodes), 20000, k, np.random.default_rng(0))
    assert future_fraction(k) == pytest.approx(fraction)
    assert batch.relabelled.mean() == pytest.approx(fraction, abs=0.015)
    relabelled = batch.relabelled
    assert np.array_equal(batch.goals[relabelled, 0], batch.episodes[relabelled])  # same episode
    assert np.array_equal(batch.goals[relabelled, 1], batch.goal_steps[relabelled])
    assert (batch.goal_steps[relabelled] > batch.steps[relabelled]).all()
    assert (batch.goal_steps[relabelled] <= 10).all()
    assert np.array_equal(batch.goals[~relabelled], episodes.goals[batch.episodes[~relabelled]])
    if k == 4.0:  # from t = 0 every later index 1 ... T is equally likely
        from_start = np.bincount(batch.goal_steps[relabelled & (batch.steps == 0)], minlength=11)[1:]
        assert from_start.min() > 0.6 * from_start.mean()
    assert np.array_equal(batch.next_achieved_goals[:, 1], batch.steps + 1)


def test_sparse_reward_is_zero_exactly_when_the_next_achieved_goal_reaches_g():
    episodes = marked_episodes(3, 10)
    batch = sample_her_transitions(filled_buffer(episodes), 5000, 4.0, np.random.default_rng(1))
    reward = SparseReward(lambda ag, g: np.linalg.norm(ag - g, axis=-1) < 0.05)(batch)
    assert np.array_equal(reward == 0, batch.goal_steps == batch.steps + 1)
    assert set(reward) == {0.0, -1.0}


def test_distance_reward_scores_s_a_g_or_the_next_state():
    episodes = marked_episodes(2, 5)
    batch = sample_her_transitions(filled_buffer(episodes), 64, 1.0, np.random.default_rng(0))
    action_distance = DistanceFunction(4, 2, 2, (8,), seed=1)
    reward = DistanceReward()
    reward.load_weights(action_distance.weights())
    assert np.allclose(reward(batch), -action_distance(batch.observations, batch.actions, batch.goals))
    state_distance = DistanceFunction(4, 0, 2, (8,), seed=1)
    reward = DistanceReward(state_distance)
    assert np.allclose(reward(batch), -state_distance(batch.next_observations, None, batch.goals))


# ------------------------------------------------------------------ learners
def small_learner(algorithm: str = "sac", q_clip: float = -50.0) -> GoalLearner:
    settings = LearnerSettings(algorithm=algorithm, hidden=(16, 16), batch_size=32, updates_per_episode=2)
    reward = SparseReward(lambda ag, g: np.linalg.norm(ag - g, axis=-1) < 0.05)
    learner = GoalLearner(settings, 4, 2, 2, 6, reward, q_clip, seed=0)
    learner.add_episodes(marked_episodes(3, 6))
    return learner


def test_q_targets_are_clipped_to_the_table_19_range():
    learner = small_learner(q_clip=-50.0)
    rewards = torch.tensor([-1.0, 0.0, -1.0])
    next_values = torch.tensor([-100.0, 30.0, -10.0])
    assert learner.q_targets(rewards, next_values).tolist() == pytest.approx([-50.0, 0.0, -10.8])
    assert default_q_clip("sparse", 0.98, 50) == pytest.approx(-50.0)
    assert default_q_clip("distance", 0.98, 50) == -1275.0


def test_reward_scale_multiplies_rewards_and_the_derived_clip():
    settings = LearnerSettings(hidden=(8,), batch_size=16, reward_scale=0.5)
    reward = SparseReward(lambda ag, g: np.zeros(len(ag), dtype=bool))
    learner = GoalLearner(settings, 4, 2, 2, 6, reward, -50.0, seed=0)
    learner.add_episodes(marked_episodes(2, 6))
    assert (learner.sample()[1] == -0.5).all() and learner.q_clip_low == -25.0


@pytest.mark.parametrize("algorithm", ["sac", "ddpg"])
def test_learner_updates_and_state_round_trip(algorithm, tmp_path):
    """Export through .npz + .json (no pickle), import into a fresh learner: identical next updates."""
    learner = small_learner(algorithm)
    learner.train(updates=3)
    save_state(learner.state(), tmp_path / "learner")
    twin = GoalLearner(learner.settings, 4, 2, 2, 6, learner.reward, learner.q_clip_low, seed=123)
    twin.load(load_state(tmp_path / "learner"))
    assert learner.train(updates=3) == twin.train(updates=3)
    obs, goals = np.zeros((5, 4)), np.ones((5, 2))
    assert np.array_equal(learner.act(obs, goals), twin.act(obs, goals))


def test_policy_explores_with_random_actions_and_rebuilds_from_weights():
    learner = small_learner("ddpg")
    policy = GoalPolicy.from_weights(learner.policy_weights(), seed=0)
    obs, goals = np.random.default_rng(0).normal(size=(2000, 4)), np.zeros((2000, 2))
    assert np.allclose(policy.act(obs, goals, explore=False), learner.act(obs, goals, explore=False))
    greedy = policy.act(obs, goals, explore=False)
    explored = policy.act(obs, goals, explore=True)
    assert (np.abs(explored) <= 1).all()
    far = np.abs(explored - greedy).max(axis=1) > 0.8  # noise 0.2 rarely moves an action that far
    assert 0.15 < far.mean() < 0.35  # random actions with probability 0.3
    policy.random_eps = 0.0
    noise = policy.act(obs, goals, explore=True) - greedy
    assert noise.std() == pytest.approx(0.2, abs=0.02)  # DDPG Gaussian action noise 0.2 (Table 19)


def test_input_normalisation_clips_raw_and_normalised_values():
    """Inputs clipped to +-200, standardised with a std floor of 0.01, then clipped to +-5 (Table 19 = baselines)."""
    from workers.distance.normalizer import RunningNormalizer

    normalizer = RunningNormalizer(2)
    normalizer.update(np.array([[1e6, 3.0], [-1e6, 3.0]]))  # clipped to +-200 before the statistics
    assert normalizer.mean.tolist() == [0.0, 3.0] and normalizer.std.tolist() == [200.0, 0.01]
    assert normalizer.normalize(np.array([[100.0, 3.0], [1e9, 3.5]])).tolist() == [[0.5, 0.0], [1.0, 5.0]]


# ----------------------------------------------------------------- settings
@pytest.mark.parametrize(
    "make",
    [
        lambda: CountSettings(single_key_dim=0),
        lambda: CountSettings(pair_key_dim=0),
        lambda: CountSettings(sigma=0.0),
        lambda: CountSettings(sigma=-1.0),
        lambda: LearnerSettings(her_k=-1.0),
        lambda: LearnerSettings(algorithm="td3"),
        lambda: DistanceSettings(conditioning="state"),
        lambda: DistanceSettings(batch_size=0),
        lambda: LoopSettings(methd="ours_her"),
        lambda: LoopSettings(method="ours_her", counts=dict(sigma=0)).resolved(),
        lambda: LoopSettings(method="sparse_her", distance=dict(batch_size=3)).resolved(),
    ],
)
def test_invalid_settings_are_clear_errors(make):
    with pytest.raises((ValidationError, ValueError)):
        make()


def test_errors_name_the_field():
    with pytest.raises(ValidationError, match="sigma"):
        CountSettings(sigma=0)
    with pytest.raises(ValidationError, match="her_k"):
        LearnerSettings(her_k=-0.5)
    with pytest.raises(ValueError, match="key dimension"):
        RandomProjectionHash(3, 0, 1.0, np.random.default_rng(0))
    with pytest.raises(ValueError, match="sigma"):
        RandomProjectionHash(3, 4, 0.0, np.random.default_rng(0))
    with pytest.raises(ValueError, match="HER k"):
        future_fraction(-1)


def test_method_settings_follow_tables_19_and_20():
    ours = method_settings("ours_her", "point_maze")
    assert (ours.counts.single_key_dim, ours.counts.pair_key_dim, ours.counts.sigma) == (64, 32, 20.0)
    assert ours.learner.her_k == 0.25 and ours.learner.algorithm == "sac" and ours.distance.triangular
    fpp = method_settings("offpolicy_ddl_her", "fetch_pick_place")
    assert fpp.learner.algorithm == "ddpg" and not fpp.distance.triangular
    assert (fpp.counts.single_key_dim, fpp.counts.pair_key_dim, fpp.counts.sigma) == (32, 64, 3.7)
    ddl = method_settings("ddl_her", "point_maze")
    assert ddl.distance.conditioning == "state" and ddl.distance.hidden == (256, 256)
    assert ddl.distance.buffer_size == 100_000
    assert method_settings("ddl_her", "fetch_pick_place_wall").learner.her_k == 8
    assert method_settings("sparse_her", "fetch_reach").distance is None


# --------------------------------------------------------------- maze truth
TINY_U = [
    [1, 1, 1, 1, 1],
    [1, 0, 1, 0, 1],
    [1, 0, 1, 0, 1],
    [1, 0, 0, 0, 1],
    [1, 1, 1, 1, 1],
]


def test_maze_distance_goes_around_walls():
    """Around the wall block of a U: two diagonals to the wall's corners and its width (clearance 0)."""
    maze = MazeDistance(TINY_U, resolution=0.05, clearance=0.0)
    around = 2 * np.hypot(0.5, 1.5) + 1.0
    distances = maze.distance(np.array([[-1.0, 1.0], [-1.0, 1.0], [-1.0, -1.0]]), np.array([[1, 1], [-1, -1], [1, -1]]))
    assert distances[0] == pytest.approx(around, rel=0.015)
    assert distances[1:] == pytest.approx([2.0, 2.0], abs=0.03)
    assert maze.distance(np.array([[-1.0, 1.0]]), np.array([-1.0, 1.0]))[0] == pytest.approx(0.0, abs=0.05)
    # The ball's radius keeps it off the corners: longer path.
    wide = MazeDistance(TINY_U, resolution=0.05, clearance=0.1).distance(np.array([[-1.0, 1.0]]), np.array([1, 1]))
    assert wide[0] > distances[0] + 0.05


def test_maze_distance_is_infinite_between_closed_rooms():
    closed = [[1, 1, 1, 1, 1], [1, 0, 1, 0, 1], [1, 1, 1, 1, 1]]
    assert MazeDistance(closed).distance(np.array([[-1.0, 0.0]]), np.array([1.0, 0.0]))[0] == np.inf


# ------------------------------------------------------------ whole loop
TINY_LOOP = dict(
    episodes_per_iteration=1,
    eval_episodes=1,
    learner=dict(hidden=(16, 16), batch_size=32, updates_per_episode=3),
    distance=dict(hidden=(16, 16), batch_size=32, temporal_updates_per_episode=3, triangular_updates_per_episode=3),
)


def test_collected_episodes_have_the_task_layout():
    from workers.tasks.goal_tasks import make_goal_task

    task = make_goal_task("fetch_pick_place")
    env = task.make_env()
    episodes, stats = collect_episodes(task, env, lambda s, g: np.zeros(4), 2, np.random.default_rng(0))
    env.close()
    assert episodes.observations.shape == (2, 51, 25) and episodes.achieved_goals.shape == (2, 51, 6)
    assert np.array_equal(episodes.achieved_goals, task.achieved_goal(episodes.observations))
    assert np.array_equal(episodes.goals[:, :3], episodes.goals[:, 3:])  # App. E.2: gripper target = box target
    assert set(stats) >= {"success", "success_any", "env_success", "final_goal_distance"}


@pytest.mark.parametrize("method", ["ours_her", "sparse_her", "ddl_her"])
def test_loop_state_round_trip_continues_identically(method, tmp_path):
    settings = LoopSettings(
        method=method,
        task="fetch_reach",
        seed=3,
        **(TINY_LOOP if method != "sparse_her" else {k: v for k, v in TINY_LOOP.items() if k != "distance"}),
    )
    first = NeuralAPSP(settings)
    metrics = first.iteration()
    if method != "sparse_her":  # episodes are merged before the distance trains: iteration 0 trains too
        assert metrics["distance/temporal_loss"] > 0
    save_state(first.state(), tmp_path / "loop")
    second = NeuralAPSP(settings)
    second.load(load_state(tmp_path / "loop"))
    untimed = lambda metrics: {k: v for k, v in metrics.items() if not k.startswith("time/")}  # noqa: E731
    assert untimed(first.iteration()) == untimed(second.iteration())
    first.close()
    second.close()


def test_state_files_hold_no_pickled_objects(tmp_path):
    trainer = DistanceTrainer(
        DistanceSettings(hidden=(8,), temporal_updates_per_episode=1, triangular_updates_per_episode=1, batch_size=8),
        CountSettings(single_key_dim=4, pair_key_dim=4, sigma=1.0),
        4,
        2,
        2,
        5,
    )
    trainer.add_episodes(marked_episodes(2, 5))
    trainer.train()
    save_state(trainer.state(), tmp_path / "trainer")
    with np.load(tmp_path / "trainer.npz", allow_pickle=False) as data:
        assert all(data[key].dtype != object for key in data.files)
    restored = load_state(tmp_path / "trainer")
    assert isinstance(restored, State) and restored.meta["recent"] is True


def test_measure_learner_updates_reports_both_rates():
    from workers.distance.bench import measure_learner_updates

    figures = measure_learner_updates(
        LearnerSettings(hidden=(16,), batch_size=16), 4, 2, 2, horizon=5, updates=4, blocks=2, distance_hidden=(8,)
    )
    assert figures["learner_updates_per_second"] > 0 and figures["bare_updates_per_second"] > 0
    assert figures["updates_per_side"] == 4.0


@pytest.mark.slow
def test_sparse_her_learns_fetch_reach_within_minutes():
    """The whole loop (collection, HER, SAC, evaluation) on FetchReach: success rises from ~0 to most episodes."""
    loop = NeuralAPSP(LoopSettings(method="sparse_her", task="fetch_reach", episodes_per_iteration=2, eval_episodes=10))
    history = loop.run(12)
    loop.close()
    successes = [metrics["eval/success"] for metrics in history]
    assert successes[0] <= 0.3
    assert max(successes[-3:]) >= 0.7, successes
