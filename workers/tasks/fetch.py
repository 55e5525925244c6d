"""Fetch Pick&Place with the sparse-in-the-thesis reward (section 3.3.1)."""

from __future__ import annotations

import gymnasium as gym
import numpy as np

from workers.tasks.base import Frame, GroundTruthTask, RolloutBatch, StepOutcome

GRIPPER_BODY = "robot0:gripper_link"
"""Body welded to the mocap target that the arm follows."""
OBJECT_SITE = "object0"


class FetchPickPlaceSparse(GroundTruthTask):
    """Fetch Pick&Place, reward -||box - target|| only (50 steps).

    "Sparse" in the thesis's sense: there is no gripper-to-box term, so the
    reward does not change until the box moves. This is gymnasium-robotics'
    FetchPickAndPlaceDense reward. Success (the figure of Table 3): the box is
    within 0.05 of the target at the end of the episode.

    The arm is driven through a mocap weld: every step sets the mocap target to
    the gripper body's (stale) pose plus 0.05 a[:3], and the finger position
    actuators to their current joint positions plus a[3]. Both depend on the
    simulated state, so the batch evaluator advances one environment step (20
    physics substeps) at a time and recomputes these controls for the whole
    batch between steps.
    """

    name = "fetch_pick_place_sparse"
    env_id = "FetchPickAndPlaceDense-v4"
    episode_length = 50
    frame_skip = 20
    action_dim = 4
    colored_noise_beta = 3.0
    frames = (
        Frame("pos", "xbody", GRIPPER_BODY),
        Frame("quat", "xbody", GRIPPER_BODY),
        Frame("pos", "site", OBJECT_SITE),
    )
    feedback_control = True
    has_success = True
    description = "Fetch arm puts a box on a target; reward -||box-target||, success rate (50 steps)"

    position_step = 0.05
    """Largest mocap displacement per step (gymnasium-robotics Fetch)."""
    gripper_quat_delta = np.array([1.0, 0.0, 1.0, 0.0])
    """Added to the gripper quaternion to form the mocap orientation (fixed end-effector rotation)."""

    def _goal(self, env: gym.Env) -> np.ndarray:
        return env.unwrapped.goal.copy()

    def controls(self, model, state, actions):
        raise NotImplementedError("fetch controls depend on the simulated state")

    def feedback_controls(self, model, state, actions_t, physics, frames):
        actions_t = np.clip(actions_t, -1.0, 1.0)
        qpos = self.qpos(model, physics)
        ctrl = np.empty((actions_t.shape[0], model.nu))
        for i in range(model.nu):
            if model.actuator_biastype[i] == 0:
                ctrl[:, i] = actions_t[:, 3]
            else:  # position actuator: target relative to the joint's current position
                ctrl[:, i] = qpos[:, model.jnt_qposadr[model.actuator_trnid[i, 0]]] + actions_t[:, 3]
        gripper_pos = frames[:, self.frame_slice(GRIPPER_BODY, "pos")]
        gripper_quat = frames[:, self.frame_slice(GRIPPER_BODY, "quat")]
        mocap_pos = gripper_pos + actions_t[:, :3] * self.position_step
        mocap_quat = gripper_quat + self.gripper_quat_delta
        return np.concatenate([ctrl, mocap_pos, mocap_quat], axis=1)

    def _distance(self, batch: RolloutBatch) -> np.ndarray:
        box = batch.frames[..., self.frame_slice(OBJECT_SITE)]
        return np.linalg.norm(box - batch.goal, axis=-1)

    def rewards(self, model, batch):
        return -self._distance(batch)

    def episode_success(self, goal_achieved: list[bool]) -> bool | None:
        return bool(goal_achieved[-1]) if goal_achieved else False

    def step_env(self, env, action):
        observation, reward, _, _, info = env.step(self.env_action(action))
        return StepOutcome(float(reward), bool(info["is_success"]), observation)
