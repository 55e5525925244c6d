"""Batched evaluation of action sequences in native MuJoCo code.

All trajectories of a batch are simulated by ``mujoco.rollout`` in C++ threads;
Python touches the batch once per call (open-loop tasks) or once per
environment step (tasks whose controls depend on the simulated state), never
once per trajectory. Rewards are vectorised numpy over the whole batch.
"""

from __future__ import annotations

import os

import mujoco
import numpy as np
from mujoco import rollout as mj_rollout

from workers.tasks.base import GroundTruthTask, RolloutBatch, SimState


def default_threads() -> int:
    """Threads for rollouts: the CPUs this process may run on."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not Linux
        return max(1, os.cpu_count() or 1)


class BatchEvaluator:
    """Simulates batches of action sequences from a captured state of a task.

    Args:
        task: the task whose planning model, controls and rewards are used.
        model: the task's planning model (:meth:`GroundTruthTask.build_planning_model`).
        threads: C++ threads for the rollouts; 0 runs on the calling thread.
    """

    def __init__(self, task: GroundTruthTask, model: mujoco.MjModel, threads: int | None = None):
        self.task = task
        self.model = model
        self.threads = default_threads() if threads is None else int(threads)
        if self.threads < 0:
            raise ValueError(f"threads must be >= 0, got {threads}")
        self._datas = [mujoco.MjData(model) for _ in range(max(1, self.threads))]
        self._pool = mj_rollout.Rollout(nthread=self.threads)
        self._control_spec = task.control_spec(model)

    def close(self) -> None:
        """Stop the rollout threads."""
        self._pool.close()

    def __enter__(self) -> BatchEvaluator:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def _run(self, initial: np.ndarray, control: np.ndarray, nstep: int, warmstart: np.ndarray | None):
        return self._pool.rollout(
            self.model,
            self._datas,
            initial_state=initial,
            control=control,
            control_spec=self._control_spec,
            nstep=nstep,
            initial_warmstart=warmstart,
        )

    def simulate(
        self, state: SimState, actions: np.ndarray, keep_substeps: bool = False, draws: np.ndarray | None = None
    ) -> RolloutBatch:
        """Simulate N action sequences (N, h, d) in [-1, 1] from ``state``.

        ``draws`` (N, h, noise_dim): standard-normal draws of a noisy task's noise process, one set per
        sequence and step (:meth:`GroundTruthTask.noisy_actions`); None simulates without noise. The batch
        records the chosen actions, not the noisy ones.
        """
        actions = np.asarray(actions, dtype=np.float64)
        if actions.ndim != 3 or actions.shape[2] != self.task.action_dim or 0 in actions.shape:
            raise ValueError(
                f"actions must be (N, horizon, {self.task.action_dim}) for {self.task.name}, got shape {actions.shape}"
            )
        if not np.isfinite(actions).all():
            raise ValueError("actions contain NaN or infinite values")
        n, horizon, _ = actions.shape
        if draws is not None:
            draws = np.asarray(draws, dtype=np.float64)
            if not self.task.noise_dim or not self.task.feedback_control:
                raise ValueError(f"{self.task.name} has no noise process that draws could drive")
            if draws.shape != (n, horizon, self.task.noise_dim):
                raise ValueError(f"draws must be {(n, horizon, self.task.noise_dim)}, got shape {draws.shape}")
        self.task.load_into(self.model, state)
        skip = self.task.frame_skip
        warmstart = state.warmstart[None]
        before_last = None
        if not self.task.feedback_control:
            control = np.repeat(self.task.controls(self.model, state, actions), skip, axis=1)
            substeps, sensors = self._run(state.physics[None], control, horizon * skip, warmstart)
            states = substeps[:, skip - 1 :: skip]
            frames = sensors[:, skip - 1 :: skip]
            if keep_substeps:
                before_last = self._before_last(state, substeps, skip)
        else:
            physics = np.repeat(state.physics[None], n, axis=0)
            current_frames = np.repeat(state.frames[None], n, axis=0)
            states = np.empty((n, horizon, physics.shape[1]))
            frames = np.empty((n, horizon, current_frames.shape[1]))
            if keep_substeps:
                before_last = np.empty_like(states)
            for t in range(horizon):
                actions_t = actions[:, t]
                if draws is not None:
                    actions_t = self.task.noisy_actions(actions_t, current_frames, draws[:, t])
                control = self.task.feedback_controls(self.model, state, actions_t, physics, current_frames)
                # The solver warm start is only known for the captured state; later
                # steps start cold (differences at the solver's tolerance).
                substeps, sensors = self._run(physics, control[:, None, :], skip, warmstart if t == 0 else None)
                physics, current_frames = substeps[:, -1], sensors[:, -1]
                states[:, t], frames[:, t] = physics, current_frames
                if keep_substeps:
                    before_last[:, t] = substeps[:, -2] if skip > 1 else (state.physics if t == 0 else states[:, t - 1])
        return RolloutBatch(state.physics, states, frames, actions, state.goal, before_last)

    @staticmethod
    def _before_last(state: SimState, substeps: np.ndarray, skip: int) -> np.ndarray:
        if skip > 1:
            return substeps[:, skip - 2 :: skip]
        start = np.broadcast_to(state.physics, substeps[:, :1].shape)
        return np.concatenate([start, substeps[:, :-1]], axis=1)

    def costs(self, state: SimState, actions: np.ndarray, draws: np.ndarray | None = None) -> np.ndarray:
        """(N,) planning cost of each sequence: the task's per-step costs summed over the horizon."""
        batch = self.simulate(state, actions, draws=draws)
        return self.task.costs(self.model, batch).sum(axis=1)

    def rewards(self, state: SimState, actions: np.ndarray, draws: np.ndarray | None = None) -> np.ndarray:
        """(N, h) per-step rewards, equal to those of the real environment (given its noise draws, if any)."""
        batch = self.simulate(state, actions, keep_substeps=self.task.needs_substeps, draws=draws)
        return self.task.rewards(self.model, batch)
