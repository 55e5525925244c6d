"""Episode storage shared by the distance trainer and the learners.

Both sample from whole episodes: the temporal loss pairs two steps of one
episode (eq. 31a), HER relabels with a later achieved goal of the same episode
(section 6.3.1). Episodes therefore stay intact, as fixed-length blocks in a
ring buffer (the thesis's episodes have a fixed horizon, App. E.3.1).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from workers.distance.state import State


class Episodes(NamedTuple):
    """E episodes of T steps; this is what collectors hand to the trainers."""

    observations: np.ndarray
    """(E, T + 1, obs_dim) observations s_0 ... s_T (the last one is after the last action)."""
    actions: np.ndarray
    """(E, T, action_dim) actions a_0 ... a_{T-1} in [-1, 1]."""
    achieved_goals: np.ndarray
    """(E, T + 1, goal_dim) ag(s_0) ... ag(s_T)."""
    goals: np.ndarray
    """(E, goal_dim) desired goal of each episode (fixed during an episode)."""
    successes: np.ndarray
    """(E, T) the task's success flag after every step (for reports; never used for learning)."""

    @property
    def horizon(self) -> int:
        return self.actions.shape[1]

    def __len__(self) -> int:
        return self.actions.shape[0]

    def select(self, index: np.ndarray | slice) -> Episodes:
        """A subset of the episodes."""
        return Episodes(*(array[index] for array in self))

    @staticmethod
    def concatenate(parts: list[Episodes]) -> Episodes:
        """Episodes of several batches, in order."""
        return Episodes(*(np.concatenate(arrays) for arrays in zip(*parts)))


class EpisodeBuffer:
    """Ring buffer of fixed-length episodes; the oldest episode is overwritten first.

    Args:
        capacity: transitions to keep; the buffer holds capacity // horizon episodes (at least one).
        horizon: steps T per episode.
        obs_dim, action_dim, goal_dim: vector sizes.
    """

    def __init__(self, capacity: int, horizon: int, obs_dim: int, action_dim: int, goal_dim: int):
        self.horizon = horizon
        self.max_episodes = max(1, capacity // horizon)
        self.dims = (obs_dim, action_dim, goal_dim)
        shape = (self.max_episodes,)
        # float32 halves the memory of a 1e6-transition buffer; zeros are allocated lazily by the OS.
        self.observations = np.zeros(shape + (horizon + 1, obs_dim), dtype=np.float32)
        self.actions = np.zeros(shape + (horizon, action_dim), dtype=np.float32)
        self.achieved_goals = np.zeros(shape + (horizon + 1, goal_dim), dtype=np.float32)
        self.goals = np.zeros(shape + (goal_dim,), dtype=np.float32)
        self.successes = np.zeros(shape + (horizon,), dtype=np.float32)
        self.size = 0
        self.next = 0
        self.episodes_added = 0

    def add(self, episodes: Episodes) -> np.ndarray:
        """Store episodes; returns the slots they went to."""
        if episodes.horizon != self.horizon:
            raise ValueError(f"episodes have {episodes.horizon} steps, the buffer holds {self.horizon}-step episodes")
        count = len(episodes)
        slots = (self.next + np.arange(count)) % self.max_episodes
        for name, array in zip(Episodes._fields, episodes):
            getattr(self, name)[slots] = array
        self.next = int((self.next + count) % self.max_episodes)
        self.size = min(self.size + count, self.max_episodes)
        self.episodes_added += count
        return slots

    def episodes(self, slots: np.ndarray | None = None) -> Episodes:
        """Stored episodes (all of them by default)."""
        index = np.arange(self.size) if slots is None else slots
        return Episodes(*(getattr(self, name)[index] for name in Episodes._fields))

    def __len__(self) -> int:
        return self.size

    @property
    def transitions(self) -> int:
        return self.size * self.horizon

    def state(self) -> State:
        """The filled part of the buffer and its write position."""
        arrays = {name: getattr(self, name)[: self.size].copy() for name in Episodes._fields}
        return State(arrays, {"size": self.size, "next": self.next, "episodes_added": self.episodes_added})

    def load(self, state: State) -> None:
        """Restore a buffer exported by :meth:`state` (same capacity and shapes)."""
        size = int(state.meta["size"])
        if size > self.max_episodes:
            raise ValueError(f"state holds {size} episodes, this buffer only {self.max_episodes}")
        for name in Episodes._fields:
            target = getattr(self, name)
            target[:size] = state.arrays[name]
            target[size : max(size, self.size)] = 0  # only slots that held episodes (untouched pages stay lazy)
        self.size, self.next = size, int(state.meta["next"])
        self.episodes_added = int(state.meta["episodes_added"])
