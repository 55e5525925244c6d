"""The model-predictive control loop: plan, execute the first action, repeat.

One episode of a task in its real environment. At every step the real
environment's state is captured, the planner optimises an action sequence
against an evaluator started from that state, and the first action is
executed in the real environment.

:class:`MpcEpisode` runs an episode in segments and can be checkpointed
between them: the environment's simulator state, the planner's memory and
random state, and the records so far are enough to continue bit for bit in
another process (the restore is exact for every task whose
``test_restore_reproduces_the_following_steps`` holds at zero tolerance).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from functools import partial
from typing import Any, NamedTuple, Protocol

import gymnasium as gym
import numpy as np

from workers.data import Trajectory, TrajectoryRecorder
from workers.planning import CEMPlanner
from workers.planning.icem import CostBatch
from workers.tasks import GroundTruthTask, SimState


class PlanningState(NamedTuple):
    """Where planning starts: the observation, and the simulator state when there is one."""

    observation: np.ndarray
    """The observation vector (:meth:`GroundTruthTask.observe`): what a learned model predicts from."""
    sim: SimState | None = None
    """The exact simulator state (ground-truth planning), None when planning on a learned model."""


class Evaluator(Protocol):
    """Anything that returns planning costs of action sequences (N, h, d) from a planning state."""

    def evaluate(self, state: PlanningState, actions: np.ndarray) -> np.ndarray | CostBatch: ...


class StepRecord(NamedTuple):
    """What happened at one environment step."""

    step: int
    reward: float
    goal_achieved: bool | None
    planning_seconds: float
    trajectories: int
    best_cost: float
    components: dict[str, float] = {}
    """The evaluator's cost terms of the executed plan (c, c_A, u_A, ... with a noisy ensemble), else empty."""


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
    components: dict[str, float] = {}
    """Means over the episode's steps of the executed plans' cost terms (empty for plain costs)."""

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


_RECORD_FIELDS = ("reward", "goal_achieved", "planning_seconds", "trajectories", "best_cost")


class MpcEpisode:
    """One MPC episode of ``task`` in ``env``, run in segments.

    Args:
        task: the task.
        env: its real environment (reset here with ``seed``).
        planner: the planner (reset here with ``seed``).
        evaluator: where planning costs come from.
        seed: the episode's seed (environment reset, and planner noise unless ``planner_seed`` is given).
        steps: environment steps of the episode.
        record_states: keep the simulator state of every step in the trajectory (for relabeling).
        planner_seed: seed of the planner's noise, when it differs from the reset's.
    """

    def __init__(
        self,
        task: GroundTruthTask,
        env: gym.Env,
        planner: CEMPlanner,
        evaluator: Evaluator,
        seed: int,
        steps: int,
        record_states: bool = False,
        planner_seed: int | None = None,
    ):
        self.task, self.env, self.planner, self.evaluator = task, env, planner, evaluator
        self.seed, self.steps, self.record_states = seed, steps, record_states
        self.planner_seed = seed if planner_seed is None else planner_seed
        self.records: list[StepRecord] = []
        self.observation, goals = self._reset()
        self.recorder = TrajectoryRecorder(self.observation, goals)

    def _reset(self):
        observation, _info = self.env.reset(seed=self.seed)
        self.planner.reset(self.planner_seed)
        return self.task.observe(observation), self.task.goals(observation)

    @property
    def t(self) -> int:
        """Steps taken so far."""
        return len(self.records)

    @property
    def done(self) -> bool:
        return self.t >= self.steps

    def run(self, until: int | None = None, on_step: Callable[[StepRecord], None] | None = None) -> list[StepRecord]:
        """Run steps up to step ``until`` (default: the episode's end); return their records."""
        until = self.steps if until is None else min(until, self.steps)
        new: list[StepRecord] = []
        while self.t < until:
            sim = self.task.capture(self.env)
            state = PlanningState(self.observation, sim)
            started = time.perf_counter()
            result = self.planner.plan(partial(self.evaluator.evaluate, state))
            seconds = time.perf_counter() - started
            outcome = self.task.step_env(self.env, result.action)
            self.observation = self.task.observe(outcome.observation)
            self.recorder.add(
                result.action,
                outcome.reward,
                self.observation,
                state=sim if self.record_states else None,
                goals=self.task.goals(outcome.observation),
            )
            record = StepRecord(
                self.t,
                outcome.reward,
                outcome.goal_achieved,
                seconds,
                result.trajectories,
                result.best_cost,
                dict(result.components),
            )
            self.records.append(record)
            new.append(record)
            if on_step is not None:
                on_step(record)
        return new

    def result(self) -> EpisodeResult:
        """The episode's figures (complete once :attr:`done`)."""
        rewards = np.array([r.reward for r in self.records])
        achieved = [r.goal_achieved for r in self.records if r.goal_achieved is not None]
        return EpisodeResult(
            episode_return=float(rewards.sum()),
            success=self.task.episode_success(achieved) if self.task.has_success else None,
            goal_steps=int(sum(achieved)) if self.task.has_success else None,
            rewards=rewards,
            planning_seconds=np.array([r.planning_seconds for r in self.records]),
            trajectories=np.array([r.trajectories for r in self.records]),
            best_costs=np.array([r.best_cost for r in self.records]),
            horizon=self.planner.config.horizon,
            frame_skip=self.task.frame_skip,
            components={
                name: float(np.mean([r.components[name] for r in self.records]))
                for name in (self.records[0].components if self.records else ())
            },
        )

    def trajectory(self) -> Trajectory:
        """The episode so far as a :class:`Trajectory`."""
        return self.recorder.finish(self.result().success)

    # ------------------------------------------------------------ state
    def state_dict(self) -> dict[str, Any]:
        """Environment, planner and records: enough to continue the episode elsewhere."""
        records = {name: np.array([getattr(r, name) for r in self.records]) for name in _RECORD_FIELDS}
        records["goal_achieved"] = np.array([bool(r.goal_achieved) for r in self.records])
        names = self.records[0].components if self.records else ()
        records["components"] = {name: np.array([r.components[name] for r in self.records]) for name in names}
        return {
            "seed": self.seed,
            "steps": self.steps,
            "sim": self.task.capture(self.env).to_tree(),
            "planner": self.planner.state_dict(),
            "records": records,
            "trajectory": self.recorder.finish().to_tree() if self.records else {},
            "has_goal_flags": bool(self.records) and self.records[0].goal_achieved is not None,
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Continue an episode captured by :meth:`state_dict` (this one was created with the same seed)."""
        self.task.restore(self.env, SimState.from_tree(state["sim"]))
        self.planner.load_state_dict(state["planner"])
        records = state["records"]
        flags = bool(state["has_goal_flags"])
        components = records.get("components") or {}
        self.records = [
            StepRecord(
                t,
                float(records["reward"][t]),
                bool(records["goal_achieved"][t]) if flags else None,
                float(records["planning_seconds"][t]),
                int(records["trajectories"][t]),
                float(records["best_cost"][t]),
                {name: float(values[t]) for name, values in components.items()},
            )
            for t in range(len(records["reward"]))
        ]
        if self.records:
            trajectory = Trajectory.from_tree(state["trajectory"])
            self.recorder = TrajectoryRecorder.resume(trajectory)
            self.observation = trajectory.observations[-1]


def run_episode(
    task: GroundTruthTask,
    env: gym.Env,
    planner: CEMPlanner,
    evaluator: Evaluator,
    seed: int,
    steps: int | None = None,
    on_step: Callable[[StepRecord], None] | None = None,
) -> EpisodeResult:
    """Run one whole MPC episode of ``task`` in ``env`` from ``env.reset(seed=seed)``.

    Args:
        steps: environment steps to run; default the task's episode length.
        on_step: called after every step (progress display, streaming metrics).
    """
    episode = MpcEpisode(task, env, planner, evaluator, seed, task.episode_length if steps is None else steps)
    episode.run(on_step=on_step)
    return episode.result()
