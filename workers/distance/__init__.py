"""Neural all-pairs shortest path (thesis chapter 6, appendix E): learned distances as rewards for SAC/DDPG + HER.

Nothing here imports Ray or MLflow. See README.md in this folder for the
layout, the phases the service runs on separate actors, and the readings of
the thesis where it is ambiguous.
"""

from workers.distance.buffer import EpisodeBuffer, Episodes
from workers.distance.config import (
    METHODS,
    CountSettings,
    DistanceSettings,
    LearnerSettings,
    Method,
    MethodSettings,
    method_settings,
)
from workers.distance.counts import CountModels, PairCounts, StateActionCounts, collision_radius
from workers.distance.learners import SB3_DECISION, GoalLearner, GoalPolicy, default_q_clip
from workers.distance.loop import LoopSettings, NeuralAPSP, collect_episodes, distance_phase, policy_phase
from workers.distance.network import DistanceFunction, DistanceModel
from workers.distance.rewards import DistanceReward, RewardFunction, SparseReward
from workers.distance.state import State, load_state, save_state
from workers.distance.trainer import DistanceTrainer

__all__ = [
    "METHODS",
    "SB3_DECISION",
    "CountModels",
    "CountSettings",
    "DistanceFunction",
    "DistanceModel",
    "DistanceReward",
    "DistanceSettings",
    "DistanceTrainer",
    "EpisodeBuffer",
    "Episodes",
    "GoalLearner",
    "GoalPolicy",
    "LearnerSettings",
    "LoopSettings",
    "Method",
    "MethodSettings",
    "NeuralAPSP",
    "PairCounts",
    "RewardFunction",
    "SparseReward",
    "State",
    "StateActionCounts",
    "collect_episodes",
    "collision_radius",
    "default_q_clip",
    "distance_phase",
    "load_state",
    "method_settings",
    "policy_phase",
    "save_state",
]
