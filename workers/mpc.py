"""The model-predictive control loop: plan, execute the first action, repeat.

One episode of a task in its real environment. At every step the real
environment's state is captured, the planner optimises an action sequence
against an evaluator started from that state (in-process native rollouts or a
pool of simulation actors: anything with ``costs(state, actions)``), and the
first action is executed in the real environment.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from functools import partial
from typing import NamedTuple, Protocol

import gymnasium as gym
import numpy as np

from workers.planning import CEMPlanner
from workers.tasks import GroundTruthTask, SimState


class Evaluator(Protocol):
    """Anything that returns planning costs (N,) of action sequences (N, h, d) from a state."""

    def costs(self, state: SimState, actions: np.ndarray) -> np.ndarray: ...


class StepRecord(NamedTuple):
    """What happened at one environment step."""

    step: int
    reward: float
    goal_achieved: bool | None
    planning_seconds: float
    trajectories: int
    best_cost: float


class EpisodeResult(NamedTuple):
    """One MPC episode."""

    episode_return: float
    """Sum of the task's rewards over the episode (the figure of Table 3)."""
    success: bool | None
    """The task's success criterion, None for tasks without one."""
    goal_steps: int | None
    """Steps on which the task's goal condition held (DAPG success needs > 25), None without one."""
    rewards: np.ndarray
    """(T,) per-step rewards."""
    planning_seconds: np.ndarray
    """(T,) wall-clock seconds spent planning each step."""
    trajectories: np.ndarray
    """(T,) action sequences evaluated per step."""
    best_costs: np.ndarray
    """(T,) lowest planning cost found at each step (summed over the horizon)."""
    horizon: int
    """Planning horizon; trajectories x horizon = simulated environment steps."""
    frame_skip: int
    """Physics steps per environment step."""

    @property
    def simulated_steps(self) -> int:
        """Environment steps simulated by the planner over the episode."""
        return int(self.trajectories.sum()) * self.horizon

    @property
    def simulated_steps_per_second(self) -> float:
        """Planner throughput in simulated environment steps per second of planning."""
        return self.simulated_steps / max(float(self.planning_seconds.sum()), 1e-12)

    @property
    def physics_steps_per_second(self) -> float:
        """Planner throughput in physics steps (simulated steps x frame skip) per second of planning."""
        return self.simulated_steps_per_second * self.frame_skip


def run_episode(
    task: GroundTruthTask,
    env: gym.Env,
    planner: CEMPlanner,
    evaluator: Evaluator,
    seed: int,
    steps: int | None = None,
    on_step: Callable[[StepRecord], None] | None = None,
) -> EpisodeResult:
    """Run one MPC episode of ``task`` in ``env`` from ``env.reset(seed=seed)``.

    Args:
        steps: environment steps to run; default the task's episode length.
        on_step: called after every step (progress display, streaming metrics).
    """
    steps = task.episode_length if steps is None else steps
    env.reset(seed=seed)
    planner.reset(seed)
    records: list[StepRecord] = []
    achieved: list[bool] = []
    for t in range(steps):
        state = task.capture(env, time_step=t)
        started = time.perf_counter()
        result = planner.plan(partial(evaluator.costs, state))
        seconds = time.perf_counter() - started
        outcome = task.step_env(env, result.action)
        if outcome.goal_achieved is not None:
            achieved.append(outcome.goal_achieved)
        record = StepRecord(t, outcome.reward, outcome.goal_achieved, seconds, result.trajectories, result.best_cost)
        records.append(record)
        if on_step is not None:
            on_step(record)
    rewards = np.array([r.reward for r in records])
    return EpisodeResult(
        episode_return=float(rewards.sum()),
        success=task.episode_success(achieved) if task.has_success else None,
        goal_steps=int(sum(achieved)) if task.has_success else None,
        rewards=rewards,
        planning_seconds=np.array([r.planning_seconds for r in records]),
        trajectories=np.array([r.trajectories for r in records]),
        best_costs=np.array([r.best_cost for r in records]),
        horizon=planner.config.horizon,
        frame_skip=task.frame_skip,
    )
