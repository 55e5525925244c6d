"""The batch evaluator reproduces the real environments' per-step rewards.

For every task: reach a random state by stepping the real environment with
random actions, evaluate random action sequences from there with the batched
native rollouts, then replay each sequence in the real environment (reached
again the same way, so nothing depends on our own state restore) and compare
every step's reward.
"""

from __future__ import annotations

import numpy as np
import pytest

from workers.rollout import BatchEvaluator
from workers.tasks import GROUND_TRUTH_TASKS, make_task
from workers.tasks.fetch import FetchPickPlaceSparse

SEQUENCES = 3
HORIZON = 8
PREFIX_STEPS = 10

# Bitwise-equal simulations give 0 (seen for HalfCheetah, Door, Relocate and
# the point mass). Fetch re-enters the native rollout once per environment
# step, and from the second step on its constraint solver starts cold instead
# of from the environment's warm start (seen: 6e-13). Humanoid's impact term
# replays the last physics substep of each step, whose PGS solver (50
# iterations) also starts cold (seen: 1e-6 on rewards of 30-40).
TOLERANCE = {name: 1e-6 for name in GROUND_TRUTH_TASKS} | {"humanoid_standup": 1e-5}

NOISELESS = {"noisy_fetch_pick_place": {"noise_std": 0.0}}
"""Noisy tasks are compared here with their noise off; tests/test_noisy_fetch.py replays the real environment's
noise draws in the batch."""


def prefix_action(task, observation, rng):
    """Random actions; for Fetch, steer the open gripper into the box so that it moves (on the noisy task, whose
    box starts near the table's edge, over the box and down around it: pushed, the box falls off the table)."""
    if isinstance(task, FetchPickPlaceSparse):
        gripper, box = observation["observation"][:3], observation["observation"][3:6]
        above = task.noise_dim and np.linalg.norm(gripper[:2] - box[:2]) > 0.01
        target = box + (0.0, 0.0, 0.05) if above else box
        return np.append(np.clip((target - gripper) / 0.05, -1, 1), 1.0)
    return rng.uniform(-1, 1, task.action_dim)


def reach_state(task, env, seed: int):
    """Reset with ``seed`` and take PREFIX_STEPS prefix actions; same seed, same state."""
    observation, _ = env.reset(seed=seed)
    rng = np.random.default_rng(seed)
    for _ in range(PREFIX_STEPS):
        observation = task.step_env(env, prefix_action(task, observation, rng)).observation


@pytest.mark.parametrize("name", sorted(GROUND_TRUTH_TASKS))
def test_batch_rewards_equal_real_environment(name, task_bundle):
    task, env, model = task_bundle(name)
    if name in NOISELESS:
        task = make_task(name, NOISELESS[name])
        env = task.make_env()
    seed = 11
    reach_state(task, env, seed)
    state = task.capture(env)
    assert env.action_space.shape == (task.action_dim,)
    actions = np.random.default_rng(3).uniform(-1.2, 1.2, (SEQUENCES, HORIZON, task.action_dim))
    with BatchEvaluator(task, model, threads=2) as evaluator:
        batch_rewards = evaluator.rewards(state, actions)
    assert batch_rewards.shape == (SEQUENCES, HORIZON)

    for n in range(SEQUENCES):
        reach_state(task, env, seed)
        env_rewards = [task.step_env(env, actions[n, t]).reward for t in range(HORIZON)]
        np.testing.assert_allclose(batch_rewards[n], env_rewards, rtol=0, atol=TOLERANCE[name])
    # Different sequences earn different rewards, so agreement is not an accident of a constant.
    assert np.ptp(batch_rewards.sum(axis=1)) > 1e-4
