"""Rewards computed when a batch is drawn (section 6.6: "4 kinds of reward coupled with HER").

The learner never stores rewards. A reward is any callable from a batch of
relabelled transitions to rewards; it runs at sampling time, so the learned
distance rewards always use the newest weights the distance trainer sent
(stored rewards would go stale as d_theta keeps changing), and HER's relabelled
goals need fresh rewards anyway.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from workers.distance.her import GoalTransitions
from workers.distance.network import DistanceFunction
from workers.distance.state import State

RewardFunction = Callable[[GoalTransitions], np.ndarray]
"""Maps a batch of B transitions (obs, action, next obs, achieved goals, goal) to B rewards."""

SuccessTest = Callable[[np.ndarray, np.ndarray], np.ndarray]
"""(achieved goals, goals) -> bool success per row; a task's ``is_success``."""


class SparseReward:
    """Sparse+HER: 0 when ag(s_{t+1}) reaches g, -1 otherwise (section 6.3.1)."""

    kind = "sparse"

    def __init__(self, success: SuccessTest):
        self.success = success

    def __call__(self, batch: GoalTransitions) -> np.ndarray:
        return np.where(self.success(batch.next_achieved_goals, batch.goals), 0.0, -1.0)


class DistanceReward:
    """The negative learned distance (DDL+HER, Off-policy DDL+HER, Ours+HER).

    d(s, a, g) scores the transition's own (s_t, a_t): -d(s_t, a_t, g), "the
    steps still needed after taking a_t". DDL's d(s, g) has no action; it
    scores the state the action led to, -d(s_{t+1}, g), so the reward still
    depends on a_t.
    """

    kind = "distance"

    def __init__(self, function: DistanceFunction | None = None, floor: float | None = None):
        self.function = function
        self.floor = floor
        """Distances below it are raised to it before the sign flip (None: the network's output as it is)."""

    def load_weights(self, weights: State) -> None:
        """Install the distance trainer's latest weights."""
        if self.function is None:
            self.function = DistanceFunction.from_weights(weights)
        else:
            self.function.load_weights(weights)

    def __call__(self, batch: GoalTransitions) -> np.ndarray:
        if self.function is None:
            raise RuntimeError("DistanceReward has no weights yet: call load_weights with the trainer's reward_weights")
        if self.function.uses_action:
            distances = self.function(batch.observations, batch.actions, batch.goals)
        else:
            distances = self.function(batch.next_observations, None, batch.goals)
        if self.floor is not None:
            distances = np.maximum(distances, self.floor)
        return -distances
