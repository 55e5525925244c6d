"""Noisy-HalfCheetah (thesis App. D.1.1, D.4): noise above velocity 6, a counted ceiling."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
import torch

from workers.dynamics.costs import box_violation_probability
from workers.tasks.noisy import NoisyHalfCheetah

torch.set_num_threads(1)


def rollout(env: gym.Env, actions: np.ndarray, seed: int = 0):
    obs, _ = env.reset(seed=seed)
    observations, rewards, infos = [obs], [], []
    for action in actions:
        obs, reward, _, _, info = env.step(action)
        observations.append(obs)
        rewards.append(reward)
        infos.append(info)
    env.close()
    return np.array(observations), np.array(rewards), infos


ACTIONS = np.random.default_rng(0).uniform(-1, 1, (15, 6))


def test_below_the_velocity_threshold_it_is_plain_halfcheetah():
    plain, _, _ = rollout(gym.make("HalfCheetah-v5"), ACTIONS)
    for noise_on in ("action", "state"):
        observations, rewards, infos = rollout(NoisyHalfCheetah(noise_on=noise_on).make_env(), ACTIONS)
        assert np.abs(observations[1:, 8]).max() < 6  # never fast: the noise never switches on
        np.testing.assert_array_equal(observations, plain)
        assert not any(info["noisy_step"] for info in infos)


@pytest.mark.parametrize("noise_on", ["action", "state"])
def test_above_the_threshold_noise_is_added(noise_on):
    """With the threshold lowered below any velocity, every step is noisy and the run departs from plain."""
    plain, plain_rewards, _ = rollout(gym.make("HalfCheetah-v5"), ACTIONS)
    task = NoisyHalfCheetah(noise_on=noise_on, velocity_threshold=-1e9)
    observations, rewards, infos = rollout(task.make_env(), ACTIONS)
    assert all(info["noisy_step"] for info in infos)
    assert np.abs(observations[1] - plain[1]).max() > 1e-3
    applied = np.array([info["applied_action"] for info in infos])
    if noise_on == "action":
        assert np.abs(applied - ACTIONS).max() > 0.1 and np.all(np.abs(applied) <= 1)
        noise = (applied - ACTIONS)[np.abs(applied) < 1]
        assert noise.std() == pytest.approx(np.sqrt(0.2), rel=0.3)  # variance 0.2
    else:
        np.testing.assert_array_equal(applied, ACTIONS)
    # The reward charges the agent's own action, not the noise.
    x_velocity = np.array([info["x_velocity"] for info in infos])
    np.testing.assert_allclose(rewards, x_velocity - 0.1 * np.square(ACTIONS).sum(1))


def test_ceiling_violations_are_counted_apart_from_the_return():
    task = NoisyHalfCheetah(ceiling=-1.0)  # below the torso: every step violates
    observations, rewards, infos = rollout(task.make_env(), ACTIONS)
    metrics = task.episode_metrics(observations, rewards, infos)
    assert metrics["ceiling_violations"] == len(ACTIONS) and metrics["failure"] == 1.0
    assert metrics["return"] == pytest.approx(rewards.sum())
    assert all(info["ceiling_violation"] for info in infos)
    relaxed = NoisyHalfCheetah()
    assert relaxed.episode_metrics(observations, rewards, infos)["ceiling_violations"] == np.sum(
        observations[1:, 0] > 0.3
    )


def test_planning_cost_and_safety_box():
    task = NoisyHalfCheetah(ceiling_cost=100.0)
    obs, next_obs = torch.zeros(3, 17), torch.zeros(3, 17)
    next_obs[:, 8] = torch.tensor([1.0, 2.0, 3.0])
    next_obs[:, 0] = torch.tensor([0.0, 0.5, 0.0])
    action = torch.full((3, 6), 0.5)
    np.testing.assert_allclose(
        task.planning_cost(obs, action, next_obs).numpy(), [-1 + 0.15, -2 + 0.15 + 100, -3 + 0.15]
    )
    (box,) = task.safety_boxes
    p = box_violation_probability(torch.tensor([[0.3] + [0.0] * 16]), torch.full((1, 17), 0.1), box)
    assert p.item() == pytest.approx(0.5)


def test_noisy_halfcheetah_rejects_bad_options():
    with pytest.raises(ValueError, match="noise_on"):
        NoisyHalfCheetah(noise_on="observation").make_env()
    with pytest.raises(ValueError, match="ceiling_cost"):
        NoisyHalfCheetah(ceiling_cost=-1.0)
