"""Observations of simulated batches: what the policy sees at every predicted state of every sample.

APEX's guidance cost (eq. 15) compares each sampled action a_t with the
policy's action pi(s_t) at the state s_t that sample's own rollout predicts.
The policy takes the real environment's observation vector
(:meth:`GroundTruthTask.observe`), so every predicted state needs the
observation the environment would report there.

* Tasks with ``batch_observations`` compute them in numpy from the batch
  (states, and frames that hold the derived quantities exactly as the
  environment reads them after a step).
* Any other task falls back to a replay: for every (sample, step) the state
  before the step's last physics substep is loaded into a real environment,
  that substep is run with the step's controls, the batch's state after the
  step is put back (positions and velocities exactly as simulated; derived
  arrays as the substep's forward pass left them, stale as the environment
  reads them), and the environment's own ``_get_obs`` is called. This is what
  the environment itself does after a step (gymnasium's MujocoEnv runs
  ``mj_rnePostConstraint`` after stepping, which the replay repeats); only
  quantities of the constraint solve (contact forces) depend on the solver
  warm start of that one substep, which the batch does not keep. It costs one
  substep and one Python call per observation.
"""

from __future__ import annotations

import gymnasium as gym
import mujoco
import numpy as np

from workers.tasks.base import FULL_PHYSICS, GroundTruthTask, RolloutBatch, SimState


class ObservationReader:
    """Observation vectors after every step of simulated batches of one task.

    Args:
        task: the task.
        env: a real environment of the task used for the replay fallback
            (its state is overwritten; never the environment of an episode).
    """

    def __init__(self, task: GroundTruthTask, env: gym.Env | None = None):
        self.task = task
        self.env = env
        self.vectorised = bool(task.batch_observations)
        if not self.vectorised and env is None:
            raise ValueError(f"{task.name} has no vectorised observations: the replay needs an environment")

    @property
    def needs_substeps(self) -> bool:
        """Whether :meth:`read` needs batches simulated with ``keep_substeps`` (the replay fallback)."""
        return not self.vectorised

    def read(self, model: mujoco.MjModel, state: SimState, batch: RolloutBatch) -> np.ndarray:
        """(N, h, obs_dim) observation after every step of ``batch`` (simulated from ``state``)."""
        if self.vectorised:
            return np.asarray(self.task.observations(model, batch), dtype=np.float64)
        return self.replay(model, state, batch)

    def replay(self, model: mujoco.MjModel, state: SimState, batch: RolloutBatch) -> np.ndarray:
        """The generic fallback: replay each step's last substep in the environment and ask it."""
        if batch.before_last_substep is None:
            raise ValueError("replaying observations needs a batch simulated with keep_substeps=True")
        task, raw = self.task, self.env.unwrapped
        env_model, data = raw.model, raw.data
        for name, value in state.model_params.items():
            np.copyto(getattr(env_model, name), value)
        if batch.goal is not None:
            raw.goal = np.array(batch.goal, copy=True)
        n, horizon, _ = batch.actions.shape
        nu, nmocap = env_model.nu, env_model.nmocap
        controls = None if task.feedback_control else task.controls(model, state, batch.actions)
        out: np.ndarray | None = None
        for t in range(horizon):
            if task.feedback_control:
                start = np.repeat(state.physics[None], n, axis=0) if t == 0 else batch.states[:, t - 1]
                frames = np.repeat(state.frames[None], n, axis=0) if t == 0 else batch.frames[:, t - 1]
                step_controls = task.feedback_controls(model, state, batch.actions[:, t], start, frames)
            else:
                step_controls = controls[:, t]
            for i in range(n):
                vector = step_controls[i]
                mujoco.mj_resetData(env_model, data)
                mujoco.mj_setState(env_model, data, batch.before_last_substep[i, t], FULL_PHYSICS)
                data.ctrl[:] = vector[:nu]
                if nmocap:
                    data.mocap_pos[:] = vector[nu : nu + 3 * nmocap].reshape(nmocap, 3)
                    data.mocap_quat[:] = vector[nu + 3 * nmocap : nu + 7 * nmocap].reshape(nmocap, 4)
                mujoco.mj_step(env_model, data)
                mujoco.mj_rnePostConstraint(env_model, data)
                # The batch's own state after the step: the replay's differs by the solver warm start.
                # Derived arrays (read stale by the environment) are left as the replay computed them.
                mujoco.mj_setState(env_model, data, batch.states[i, t], FULL_PHYSICS)
                observation = task.observe(raw._get_obs())
                if out is None:
                    out = np.empty((n, horizon, observation.shape[0]))
                out[i, t] = observation
        return out
