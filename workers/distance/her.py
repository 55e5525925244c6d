"""Hindsight Experience Replay with the "future" strategy (section 6.3.1, Table 19).

A sampled transition (s_t, a_t, s_{t+1}) keeps its episode's desired goal with
probability 1 / (1 + k) and otherwise gets the achieved goal ag(s_f) of a
uniformly chosen later step f in [t + 1, T] of the same episode, so a fraction
k / (1 + k) is relabelled (Andrychowicz et al.'s k relabelled goals per real
one; Table 19 lists k per method). Rewards are not stored: the learner
computes them when the batch is drawn (see :mod:`workers.distance.rewards`),
because the learned distance changes after the transitions were collected.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from workers.distance.buffer import EpisodeBuffer, Episodes


class GoalTransitions(NamedTuple):
    """A batch of B goal-conditioned transitions, relabelled, without rewards."""

    observations: np.ndarray
    """(B, obs_dim) s_t."""
    actions: np.ndarray
    """(B, action_dim) a_t."""
    next_observations: np.ndarray
    """(B, obs_dim) s_{t+1}."""
    achieved_goals: np.ndarray
    """(B, goal_dim) ag(s_t)."""
    next_achieved_goals: np.ndarray
    """(B, goal_dim) ag(s_{t+1}), what the sparse reward compares with the goal."""
    goals: np.ndarray
    """(B, goal_dim) the (possibly relabelled) goal g."""
    relabelled: np.ndarray
    """(B,) bool: g is a future achieved goal rather than the episode's desired goal."""
    episodes: np.ndarray
    """(B,) buffer slot of each transition's episode."""
    steps: np.ndarray
    """(B,) t."""
    goal_steps: np.ndarray
    """(B,) f such that g = ag(s_f) for relabelled transitions, -1 otherwise."""


def future_fraction(k: float) -> float:
    """Fraction of relabelled transitions for HER k: k / (1 + k)."""
    if k < 0:
        raise ValueError(f"HER k must be >= 0, got {k}")
    return k / (1.0 + k)


def sample_her_transitions(
    buffer: EpisodeBuffer | Episodes, batch_size: int, her_k: float, rng: np.random.Generator
) -> GoalTransitions:
    """Draw transitions uniformly over the stored episodes and relabel a k / (1 + k) fraction with future goals."""
    stored = len(buffer)
    if stored == 0:
        raise ValueError("cannot sample from an empty buffer")
    horizon = buffer.actions.shape[1]
    episodes = rng.integers(stored, size=batch_size)
    steps = rng.integers(horizon, size=batch_size)
    relabelled = rng.random(batch_size) < future_fraction(her_k)
    # A future index f uniform in [t + 1, T]: ag(s_{t+1}) is already "achieved after a_t".
    future = steps + 1 + np.floor(rng.random(batch_size) * (horizon - steps)).astype(np.int64)
    goal_steps = np.where(relabelled, future, -1)
    goals = np.where(
        relabelled[:, None],
        buffer.achieved_goals[episodes, np.minimum(future, horizon)],
        buffer.goals[episodes],
    )
    return GoalTransitions(
        observations=buffer.observations[episodes, steps],
        actions=buffer.actions[episodes, steps],
        next_observations=buffer.observations[episodes, steps + 1],
        achieved_goals=buffer.achieved_goals[episodes, steps],
        next_achieved_goals=buffer.achieved_goals[episodes, steps + 1],
        goals=goals.astype(np.float32),
        relabelled=relabelled,
        episodes=episodes,
        steps=steps,
        goal_steps=goal_steps,
    )
