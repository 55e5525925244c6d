"""Locomotion tasks of chapter 3: HalfCheetah running and Humanoid standup."""

from __future__ import annotations

import math

import mujoco
import numpy as np
from pydantic import Field

from workers.tasks.base import FULL_PHYSICS, GroundTruthTask, RolloutBatch, SimState, TaskOptions


class HalfCheetahOptions(TaskOptions):
    flip_penalty: float = Field(10.0, ge=0)
    """Planning cost per step while |root angle| > pi/2 (0 switches the penalty off)."""


class HalfCheetahRunning(GroundTruthTask):
    """HalfCheetah running (section 3.3.1): run forward fast without flipping over.

    The reward, and the return reported next to Table 3, is gymnasium's
    HalfCheetah reward: forward velocity (x displacement over the 0.05 s step)
    minus 0.1 ||a||^2. The planning cost adds the thesis's flip penalty: a heavy
    cost whenever the root angle leaves [-pi/2, pi/2], which stops the planner
    from exploiting rolling motions (the authors' public code uses 10 per step).
    """

    name = "halfcheetah_running"
    env_id = "HalfCheetah-v5"
    Options = HalfCheetahOptions
    episode_length = 1000
    frame_skip = 5
    action_dim = 6
    colored_noise_beta = 0.25
    description = "HalfCheetah, forward velocity with a flip penalty (1000 steps)"

    ctrl_cost_weight = 0.1
    """Weight of ||a||^2 in gymnasium's HalfCheetah reward."""
    batch_observations = True

    def observations(self, model: mujoco.MjModel, batch: RolloutBatch) -> np.ndarray:
        # HalfCheetah-v5: qpos without the root x position, then qvel; both read from the state.
        return np.concatenate([self.qpos(model, batch.states)[..., 1:], self.qvel(model, batch.states)], axis=-1)

    def controls(self, model: mujoco.MjModel, state: SimState, actions: np.ndarray) -> np.ndarray:
        return self._with_mocap(state, actions)

    def rewards(self, model: mujoco.MjModel, batch: RolloutBatch) -> np.ndarray:
        x_after = batch.states[..., 1]  # qpos[0] is the root x position
        x_before = np.concatenate([np.broadcast_to(batch.start[1], x_after[:, :1].shape), x_after[:, :-1]], axis=1)
        dt = model.opt.timestep * self.frame_skip
        forward = (x_after - x_before) / dt
        return forward - self.ctrl_cost_weight * np.sum(np.square(batch.actions), axis=-1)

    def costs(self, model: mujoco.MjModel, batch: RolloutBatch) -> np.ndarray:
        root_angle = self.qpos(model, batch.states)[..., 2]
        flipped = np.abs(root_angle) > math.pi / 2
        return -self.rewards(model, batch) + self.options.flip_penalty * flipped


class HumanoidStandup(GroundTruthTask):
    """Humanoid standup (section 3.3.1): get the head as high as possible.

    Reward (gymnasium HumanoidStandup-v5): qpos_z / timestep - 0.1 ||ctrl||^2
    - min(5e-7 ||cfrc_ext||^2, 10) + 1. The impact term reads contact forces
    that the environment computes after each step from the last stage of the
    RK4 integrator; mujoco.rollout does not return them, so the batch reward
    replays the last physics substep of every step (mj_step +
    mj_rnePostConstraint, per state) to get them. That is slow and only used to
    verify rewards and report the return. The planning cost leaves the impact term out: it is
    bounded by 10 per step against a height term of 100-470 per step, and the
    Gym v2 environment of the thesis computed it as zero (mujoco-py 2 never
    filled cfrc_ext), so the published returns were obtained without it.
    """

    name = "humanoid_standup"
    env_id = "HumanoidStandup-v5"
    episode_length = 1000
    frame_skip = 5
    action_dim = 17
    colored_noise_beta = 2.0
    description = "Humanoid standing up from lying on the floor (1000 steps)"

    action_scale = 0.4
    """Half-width of the environment's action box (actions are normalised to [-1, 1])."""
    ctrl_cost_weight = 0.1
    impact_cost_weight = 0.5e-6
    impact_cost_max = 10.0

    def env_action(self, action: np.ndarray) -> np.ndarray:
        return self.action_scale * np.asarray(action, dtype=np.float64)

    def controls(self, model: mujoco.MjModel, state: SimState, actions: np.ndarray) -> np.ndarray:
        return self._with_mocap(state, self.env_action(actions))

    def _height_reward(self, model: mujoco.MjModel, batch: RolloutBatch) -> np.ndarray:
        height = self.qpos(model, batch.states)[..., 2]
        ctrl = self.env_action(batch.actions)
        return height / model.opt.timestep - self.ctrl_cost_weight * np.sum(np.square(ctrl), axis=-1) + 1

    @property
    def needs_substeps(self) -> bool:
        return True

    def impact_costs(self, model: mujoco.MjModel, batch: RolloutBatch) -> np.ndarray:
        """(N, h) clipped impact cost, recomputed from the state before the last substep."""
        if batch.before_last_substep is None:
            raise ValueError("humanoid_standup rewards need the states before the last substep")
        data = mujoco.MjData(model)
        ctrl = self.env_action(batch.actions)
        out = np.empty(batch.actions.shape[:2])
        for index in np.ndindex(*out.shape):
            mujoco.mj_resetData(model, data)
            mujoco.mj_setState(model, data, batch.before_last_substep[index], FULL_PHYSICS)
            data.ctrl[:] = ctrl[index]
            mujoco.mj_step(model, data)
            mujoco.mj_rnePostConstraint(model, data)
            out[index] = self.impact_cost_weight * np.square(data.cfrc_ext).sum()
        return np.clip(out, -np.inf, self.impact_cost_max)

    def rewards(self, model: mujoco.MjModel, batch: RolloutBatch) -> np.ndarray:
        return self._height_reward(model, batch) - self.impact_costs(model, batch)

    def costs(self, model: mujoco.MjModel, batch: RolloutBatch) -> np.ndarray:
        return -self._height_reward(model, batch)
