"""Tasks planned with a learned ensemble (thesis chapter 5, App. D.4).

Unlike the ground-truth tasks of workers/tasks/base.py, the planner never
restarts a simulator here: it sees only observations, and a task contributes a
real environment, a vectorised planning cost on (s, a, s') torch batches for
RAZER's evaluator (workers/dynamics/costs.py), its safety sets, and per-episode
metrics. Actions are normalised to [-1, 1] in every dimension, as in iCEM;
``env_action`` maps them to the environment, and the ensemble is trained on the
normalised actions.

Tasks are registered with the ground-truth ones (workers/tasks/__init__.py
``TASKS``), so sweeps name them and validate their options the same way:
each task has an ``Options`` model (a :class:`TaskOptions`) and is built as
``Task(**options)``. Nothing here imports torch at module level (the planning
costs import it when called), so validating a sweep stays fast.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from typing import TYPE_CHECKING, Any, ClassVar

import gymnasium as gym
import numpy as np

from workers.dynamics.settings import SafetyBox
from workers.tasks.base import TaskOptions

if TYPE_CHECKING:
    import torch


class ModelBasedTask(ABC):
    """A chapter-5 task: real environment, planning cost c(s, a, s') and episode metrics.

    Args:
        **options: values for the task's :attr:`Options` (validated; unknown keys are errors).
    """

    Options: ClassVar[type[TaskOptions]] = TaskOptions
    """The task's options model (a sweep sets them under ``task_options``)."""
    name: ClassVar[str]
    """Name the service may register the task under."""
    observation_dim: ClassVar[int]
    """Dimensions of the (flat) observation the model predicts."""
    action_dim: ClassVar[int]
    """Dimensions of the normalised action."""
    ensemble_preset: ClassVar[str]
    """Name of the EnsembleConfig preset of the thesis for this task (Tables 13/14)."""
    colored_noise_beta: ClassVar[float]
    """iCEM's colored-noise exponent for this task (Tables 15/16)."""
    description: ClassVar[str] = ""
    """One line for listings."""

    planner_defaults: ClassVar[dict[str, Any]] = {}
    """The task's differences to Table 15's planner settings (PlannerConfig fields), e.g. Table 16."""
    map_rectangles: ClassVar[tuple] = ()
    """((x0, x1), (y0, y1)) rectangles drawn under the visited-state scatter (e.g. BridgeMaze's walkways)."""
    map_walls: ClassVar[tuple] = ()
    """((x0, x1), (y0, y1)) footprints of walls and rims, drawn over the map rectangles."""
    coverage_range: ClassVar[tuple | None] = None
    """((x0, x1), (y0, y1)) extent of the visited-state plane, if the task has one."""
    plane_probe: ClassVar[str] = ""
    """What the states of :meth:`plane_states` are, in a few words (the title of a map of the model)."""
    has_success: ClassVar[bool] = False
    """Whether :meth:`episode_metrics` reports ``success``."""

    episode_length: int
    """Environment steps per episode."""

    def __init__(self, **options: Any):
        self.options = self.Options(**options)

    @abstractmethod
    def make_env(self) -> gym.Env:
        """The real environment with the task's time limit; ``step`` takes normalised actions via env_action."""

    def env_action(self, action: np.ndarray) -> np.ndarray:
        """Map a normalised action in [-1, 1] to the environment's action space."""
        return np.clip(np.asarray(action, dtype=np.float64), -1.0, 1.0)

    @abstractmethod
    def planning_cost(self, obs: torch.Tensor, action: torch.Tensor, next_obs: torch.Tensor) -> torch.Tensor:
        """c(s, a, s') for (B, d), (B, d_a), (B, d) batches -> (B,) (the negative task reward)."""

    def project_states(self, states: torch.Tensor) -> torch.Tensor:
        """States a model predicted during planning, moved onto the set real states lie on (..., d) -> (..., d).

        Applied to every propagated particle and mean state (workers/dynamics/propagation.py), as PETS's
        per-environment ``obs_postproc``; not in the thesis. The identity unless a task's states obey a
        constraint the model does not know, such as a unit quaternion.
        """
        return states

    @property
    def safety_boxes(self) -> tuple[SafetyBox, ...]:
        """Violation sets for RAZER's safety term (App. D.1.3); none by default."""
        return ()

    @abstractmethod
    def episode_metrics(
        self, observations: np.ndarray, rewards: np.ndarray, infos: list[dict[str, Any]]
    ) -> dict[str, float]:
        """Metrics of one finished episode.

        Args:
            observations: (T + 1, d) observations from the reset on.
            rewards: (T,) rewards the environment returned.
            infos: the T info dicts of the steps.

        Returns at least ``return``; ``success`` and ``failure`` (0.0 / 1.0) where the task defines them.
        """

    def coverage_grid(self, observations: np.ndarray) -> np.ndarray | None:
        """Boolean grid of the state-space cells the observations visit (OR grids to accumulate); None: no grid."""
        return None

    def visited_xy(self, observations: np.ndarray) -> np.ndarray | None:
        """(n, 2) the plane the visited-state scatter (Fig. 37b/c) is drawn in; None: no such plane."""
        return None

    def plane_states(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
        """(states (n, d), model-space actions (n, d_a)) that stand for the points (n, 2) of the plane in a map of
        the model's uncertainty (workers/dynamics/uncertainty_map.py); None: the task has no plane."""
        return None
