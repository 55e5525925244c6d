"""Fetch Pick&Place with the sparse-in-the-thesis reward (section 3.3.1)."""

from __future__ import annotations

import gymnasium as gym
import mujoco
import numpy as np

from workers.tasks.base import Frame, GroundTruthTask, RolloutBatch, StepOutcome

GRIPPER_BODY = "robot0:gripper_link"
"""Body welded to the mocap target that the arm follows."""
OBJECT_SITE = "object0"
OBJECT_BODY = "object0"
"""The box's body; its site sits at the body origin without rotation, so the site's frame is the body's."""
GRIP_SITE = "robot0:grip"
"""The end-effector site of the observation (grip_pos, grip_velp)."""
ARM_CHAIN = (
    "robot0:base_link",
    "robot0:torso_lift_link",
    "robot0:shoulder_pan_link",
    "robot0:shoulder_lift_link",
    "robot0:upperarm_roll_link",
    "robot0:elbow_flex_link",
    "robot0:forearm_roll_link",
    "robot0:wrist_flex_link",
    "robot0:wrist_roll_link",
)
"""Bodies whose joints move the grip site (slides and hinges): their frames give its Jacobian."""


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
        # For observations (APEX's policy input): the grip site, the box's orientation, and the frames of
        # the arm's joint bodies (the grip site's Jacobian).
        Frame("pos", "site", GRIP_SITE),
        Frame("quat", "xbody", OBJECT_BODY),
        *(Frame(kind, "xbody", body) for body in ARM_CHAIN for kind in ("pos", "quat")),
    )
    feedback_control = True
    has_success = True
    batch_observations = True
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

    def observations(self, model, batch):
        """gymnasium-robotics' Fetch observation (25 values) and the desired goal, from the batch.

        After a step the environment reads site positions and orientations as the forward pass of the
        last substep left them (the frames) and velocities as J(those kinematics) @ qvel(now): the grip
        site's Jacobian is built here from the frames of the arm's joint bodies.
        """
        from gymnasium_robotics.utils import rotations

        dt = self.frame_skip * model.opt.timestep
        qpos, qvel = self.qpos(model, batch.states), self.qvel(model, batch.states)
        frames = batch.frames
        grip_pos = frames[..., self.frame_slice(GRIP_SITE)]
        grip_velp = self._chain_site_velocity(model, frames, grip_pos, qvel) * dt
        object_pos = frames[..., self.frame_slice(OBJECT_SITE)]
        object_matrix = rotations.quat2mat(frames[..., self.frame_slice(OBJECT_BODY, "quat")])
        object_rot = rotations.mat2euler(object_matrix)
        free = model.jnt_dofadr[mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, "object0:joint")]
        # Free joint: linear velocity of the body origin (= the site) in world axes, angular in body axes.
        object_velp = qvel[..., free : free + 3] * dt - grip_velp
        object_velr = np.einsum("...ij,...j->...i", object_matrix, qvel[..., free + 3 : free + 6]) * dt
        robot = [j for j in range(model.njnt) if model.joint(j).name.startswith("robot")][-2:]
        gripper_state = qpos[..., [model.jnt_qposadr[j] for j in robot]]
        gripper_vel = qvel[..., [model.jnt_dofadr[j] for j in robot]] * dt
        goal = np.broadcast_to(batch.goal, grip_pos.shape)
        return np.concatenate(
            [
                grip_pos,
                object_pos,
                object_pos - grip_pos,
                gripper_state,
                object_rot,
                object_velp,
                object_velr,
                grip_velp,
                gripper_vel,
                goal,
            ],
            axis=-1,
        )

    def _chain_site_velocity(self, model, frames, site_pos, qvel):
        """J(site) @ qvel for the grip site: slide joints move it along their axis, hinges rotate it about theirs."""
        from gymnasium_robotics.utils import rotations

        velocity = np.zeros(site_pos.shape)
        for body in ARM_CHAIN:
            body_id = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, body)
            rotation = rotations.quat2mat(frames[..., self.frame_slice(body, "quat")])
            origin = frames[..., self.frame_slice(body, "pos")]
            for joint in np.flatnonzero(model.jnt_bodyid == body_id):
                axis = rotation @ model.jnt_axis[joint]
                rate = qvel[..., model.jnt_dofadr[joint], None]
                if model.jnt_type[joint] == mujoco.mjtJoint.mjJNT_SLIDE:
                    velocity += axis * rate
                elif model.jnt_type[joint] == mujoco.mjtJoint.mjJNT_HINGE:
                    anchor = origin + rotation @ model.jnt_pos[joint]
                    velocity += np.cross(axis, site_pos - anchor) * rate
                else:
                    raise ValueError(f"joint {model.joint(joint).name} of the arm is neither slide nor hinge")
        return velocity

    def episode_success(self, goal_achieved: list[bool]) -> bool | None:
        return bool(goal_achieved[-1]) if goal_achieved else False

    def step_env(self, env, action):
        observation, reward, _, _, info = env.step(self.env_action(action))
        return StepOutcome(float(reward), bool(info["is_success"]), observation)
