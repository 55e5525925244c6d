"""Changes to the chapter 6 algorithm layer made for the napsp method: reward floor, sketch checkpoints, Fetch sigma."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from workers.distance.config import HASH_SIZES, SUCCESS_RADIUS, TABLE_20, method_settings
from workers.distance.counts import CountMinSketch, collision_radius
from workers.distance.her import GoalTransitions
from workers.distance.learners import default_q_clip
from workers.distance.network import DistanceFunction
from workers.distance.rewards import DistanceReward


@pytest.fixture(autouse=True)
def one_thread():
    torch.set_num_threads(1)


def batch(size: int, rng: np.random.Generator) -> GoalTransitions:
    observations = rng.normal(size=(size, 3))
    return GoalTransitions(
        observations=observations,
        actions=rng.uniform(-1, 1, (size, 2)),
        next_observations=observations + 0.1,
        achieved_goals=observations[:, :2],
        next_achieved_goals=observations[:, :2] + 0.1,
        goals=rng.normal(size=(size, 2)),
        relabelled=np.zeros(size, dtype=bool),
        episodes=np.zeros(size, dtype=int),
        steps=np.zeros(size, dtype=int),
        goal_steps=-np.ones(size, dtype=int),
    )


def test_distance_floor_keeps_rewards_non_positive():
    """A negative prediction would be a positive reward that Table 19's clip at 0 then hides: the floor stops it."""
    function = DistanceFunction(3, 2, 2, (8,), seed=0)
    with torch.no_grad():
        function.net[-1].bias.fill_(-50.0)  # every prediction negative
    data = batch(64, np.random.default_rng(0))
    raw = DistanceReward(function)(data)
    floored = DistanceReward(function, floor=0.0)(data)
    assert (raw > 0).all()
    assert (floored == 0.0).all()
    with torch.no_grad():
        function.net[-1].bias.fill_(50.0)  # positive predictions pass unchanged
    assert np.array_equal(DistanceReward(function, floor=0.0)(data), DistanceReward(function)(data))


def test_learned_rewards_are_scaled_to_the_sparse_range():
    for task in HASH_SIZES:
        ours, sparse = method_settings("ours_her", task), method_settings("sparse_her", task)
        horizon = 100 if task == "point_maze" else 50
        assert ours.learner.reward_scale == 1 / horizon and ours.learner.nonnegative_distance
        assert sparse.learner.reward_scale == 1.0 and not sparse.learner.nonnegative_distance
        # The derived Q clip scales along: -T (T + 1) / 2 / T = -(T + 1) / 2.
        assert default_q_clip("distance", 0.98, horizon) * ours.learner.reward_scale == -(horizon + 1) / 2


def test_fetch_sigma_puts_the_pair_collision_radius_at_the_success_radius():
    """Point Maze's printed sigma gives a pair radius near its success radius; the Fetch defaults follow that."""
    maze_single, maze_pair, maze_sigma = TABLE_20["point_maze"]
    assert collision_radius(maze_sigma, maze_pair) == pytest.approx(0.54, abs=0.01)  # success radius 0.45
    for task in ("fetch_reach", "fetch_reach_wall", "fetch_pick_place", "fetch_pick_place_wall"):
        single, pair, sigma = HASH_SIZES[task]
        assert (single, pair) == TABLE_20[task][:2]
        assert collision_radius(TABLE_20[task][2], pair) < SUCCESS_RADIUS[task] / 10  # printed: ~2-4 mm
        assert collision_radius(sigma, pair) == pytest.approx(SUCCESS_RADIUS[task], rel=0.02)


@pytest.mark.parametrize("codes", [300, 700_000])
def test_sketch_state_round_trips_sparse_and_dense(codes):
    """Few counts export as (cell, value) pairs, many as the whole tables; both restore the same counts."""
    rng = np.random.default_rng(0)
    sketch = CountMinSketch(8, np.random.default_rng(1))
    data = rng.integers(-1000, 1000, (codes, 8))
    sketch.add(data)
    state = sketch.state()
    assert ("tables" in state.arrays) == (codes > 500_000)  # ~6 cells per code, 8 bytes sparse vs 4 dense
    size = sum(array.nbytes for array in state.arrays.values())
    assert size <= sketch.tables.nbytes + 1000
    restored = CountMinSketch(8, np.random.default_rng(99))
    restored.load(state)
    assert np.array_equal(restored.tables, sketch.tables) and restored.total == sketch.total
    assert np.array_equal(restored.query(data[:50]), sketch.query(data[:50]))
