"""Data records shared by the methods: episodes as trajectories, and a buffer of recent ones.

Every method collects episodes in a real environment. A :class:`Trajectory`
keeps what later stages need of one: observations and actions (policy and
model training), rewards, the simulator states (DAgger relabeling plans from
them, chapter 4) and the achieved and desired goals (HER, chapter 6). Both
convert to checkpoint trees (workers.checkpoint), so datasets survive a
restart without pickling.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Iterable
from typing import Any, NamedTuple

import numpy as np

from workers.tasks.base import SimStates


class Trajectory(NamedTuple):
    """One episode of T steps in a real environment."""

    observations: np.ndarray
    """(T + 1, obs_dim) observation vectors (:meth:`GroundTruthTask.observe`), the last one after the final step."""
    actions: np.ndarray
    """(T, d) executed actions, normalised to [-1, 1]."""
    rewards: np.ndarray
    """(T,) the task's rewards."""
    sim_states: SimStates | None = None
    """The simulator state before each of the T steps (ground-truth tasks), else None."""
    achieved_goals: np.ndarray | None = None
    """(T + 1, g) achieved goals (goal-conditioned tasks), else None."""
    desired_goals: np.ndarray | None = None
    """(T + 1, g) desired goals (goal-conditioned tasks), else None."""
    success: bool | None = None
    """The task's success criterion for the episode, None for tasks without one."""

    def __len__(self) -> int:
        return len(self.actions)

    @property
    def episode_return(self) -> float:
        return float(self.rewards.sum())

    def to_tree(self) -> dict[str, Any]:
        tree: dict[str, Any] = {
            "observations": self.observations,
            "actions": self.actions,
            "rewards": self.rewards,
            "success": self.success,
        }
        if self.sim_states is not None:
            tree["sim_states"] = self.sim_states.to_tree()
        if self.achieved_goals is not None:
            tree["achieved_goals"] = self.achieved_goals
            tree["desired_goals"] = self.desired_goals
        return tree

    @classmethod
    def from_tree(cls, tree: dict[str, Any]) -> Trajectory:
        return cls(
            observations=np.asarray(tree["observations"]),
            actions=np.asarray(tree["actions"]),
            rewards=np.asarray(tree["rewards"]),
            sim_states=SimStates.from_tree(tree["sim_states"]) if "sim_states" in tree else None,
            achieved_goals=np.asarray(tree["achieved_goals"]) if "achieved_goals" in tree else None,
            desired_goals=np.asarray(tree["desired_goals"]) if "desired_goals" in tree else None,
            success=tree.get("success"),
        )


class TrajectoryRecorder:
    """Builds a :class:`Trajectory` step by step."""

    def __init__(self, observation: np.ndarray, goals: tuple[np.ndarray, np.ndarray] | None = None):
        self.observations = [np.asarray(observation, dtype=np.float64)]
        self.actions: list[np.ndarray] = []
        self.rewards: list[float] = []
        self.states: list = []
        self.goals = [goals] if goals is not None else None

    @classmethod
    def resume(cls, trajectory: Trajectory) -> TrajectoryRecorder:
        """A recorder that continues a partial trajectory."""
        goals = None
        if trajectory.achieved_goals is not None:
            goals = (trajectory.achieved_goals[0], trajectory.desired_goals[0])
        recorder = cls(trajectory.observations[0], goals)
        recorder.observations = list(trajectory.observations)
        recorder.actions = list(trajectory.actions)
        recorder.rewards = list(trajectory.rewards)
        if trajectory.sim_states is not None:
            recorder.states = [trajectory.sim_states[t] for t in range(len(trajectory.sim_states))]
        if goals is not None:
            recorder.goals = list(zip(trajectory.achieved_goals, trajectory.desired_goals))
        return recorder

    def add(self, action, reward: float, observation, state=None, goals=None) -> None:
        """Record one step: the action taken from ``state``, its reward and the observation after it."""
        self.actions.append(np.asarray(action, dtype=np.float64))
        self.rewards.append(float(reward))
        self.observations.append(np.asarray(observation, dtype=np.float64))
        if state is not None:
            self.states.append(state)
        if self.goals is not None:
            self.goals.append(goals)

    def finish(self, success: bool | None = None) -> Trajectory:
        action_dim = self.actions[0].shape[0] if self.actions else 0
        return Trajectory(
            observations=np.stack(self.observations),
            actions=np.stack(self.actions) if self.actions else np.zeros((0, action_dim)),
            rewards=np.asarray(self.rewards, dtype=np.float64),
            sim_states=SimStates.stack(self.states) if self.states else None,
            achieved_goals=np.stack([g[0] for g in self.goals]) if self.goals else None,
            desired_goals=np.stack([g[1] for g in self.goals]) if self.goals else None,
            success=success,
        )


class Transitions(NamedTuple):
    """Transitions of many episodes, flattened for training."""

    observations: np.ndarray
    """(M, obs_dim) observation before each step."""
    actions: np.ndarray
    """(M, d) action taken."""
    next_observations: np.ndarray
    """(M, obs_dim) observation after the step."""
    rewards: np.ndarray
    """(M,) reward of the step."""


class EpisodeBuffer:
    """The most recent ``capacity`` episodes (a sliding window; the oldest leave first).

    APEX trains its policy on the latest W x n rollouts (Table 11); model-based
    RL keeps every episode (``capacity`` None).
    """

    def __init__(self, capacity: int | None = None):
        if capacity is not None and capacity < 1:
            raise ValueError(f"buffer capacity must be >= 1, got {capacity}")
        self.capacity = capacity
        self.episodes: deque[Trajectory] = deque(maxlen=capacity)

    def add(self, episodes: Trajectory | Iterable[Trajectory]) -> None:
        if isinstance(episodes, Trajectory):
            episodes = [episodes]
        self.episodes.extend(episodes)

    def __len__(self) -> int:
        return len(self.episodes)

    @property
    def steps(self) -> int:
        """Transitions held."""
        return sum(len(e) for e in self.episodes)

    def transitions(self) -> Transitions:
        """Every held step as flat arrays (in episode order)."""
        if not self.episodes:
            raise ValueError("the buffer is empty")
        return Transitions(
            observations=np.concatenate([e.observations[:-1] for e in self.episodes]),
            actions=np.concatenate([e.actions for e in self.episodes]),
            next_observations=np.concatenate([e.observations[1:] for e in self.episodes]),
            rewards=np.concatenate([e.rewards for e in self.episodes]),
        )

    def to_tree(self) -> dict[str, Any]:
        return {"capacity": self.capacity, "episodes": {f"{i:06d}": e.to_tree() for i, e in enumerate(self.episodes)}}

    @classmethod
    def from_tree(cls, tree: dict[str, Any]) -> EpisodeBuffer:
        buffer = cls(tree.get("capacity"))
        episodes = tree.get("episodes") or {}
        buffer.add(Trajectory.from_tree(episodes[key]) for key in sorted(episodes))
        return buffer
