"""Adroit (DAPG) hand tasks of chapter 3: Door, Door sparse and Relocate.

The rewards are DAPG's (Rajeswaran et al. 2018), as the thesis uses them.
gymnasium-robotics 1.4.2's AdroitHand*-v1 environments add the palm distance
term with the wrong sign (+0.1 ||palm - target||), so the environment's own
reward is not used: every step's reward is computed from the real
environment's simulator data with DAPG's definition (:meth:`step_env`), and the
vectorised batch reward computes the same from sensor readings.

Success is DAPG's: the goal condition holds on more than 25 steps of the
episode.

Contact margins: MuJoCo 2 (the thesis's mujoco-py environments) took the
larger of two geoms' margins for their contact; MuJoCo adds them since 3.5.
The option ``contact_margin: max`` restores the old stand-off (see
:class:`AdroitOptions`).
"""

from __future__ import annotations

from typing import Literal

import mujoco
import numpy as np

from workers.tasks.base import Frame, GroundTruthTask, RolloutBatch, SimState, StepOutcome, TaskOptions

SUCCESS_MIN_STEPS = 25
"""DAPG's success: goal achieved on more than this many steps of an episode."""


class AdroitOptions(TaskOptions):
    contact_margin: Literal["sum", "max"] = "sum"
    """How two geoms' margins combine into their contact's margin: "sum", as MuJoCo does since 3.5 (1 mm
    here: every geom of the DAPG models has margin 0.5 mm); "max", as in MuJoCo 2, which the thesis's
    mujoco-py environments ran on (0.5 mm). "max" halves every geom margin, which is exactly the old rule
    because all margins are equal (checked when the environment is built)."""


class _AdroitTask(GroundTruthTask):
    frame_skip = 5
    episode_length = 200
    has_success = True
    Options = AdroitOptions

    def make_env(self):
        env = super().make_env()
        if self.options.contact_margin == "max":
            margins = env.unwrapped.model.geom_margin
            if np.ptp(margins) > 0:
                raise ValueError(
                    f"{self.name}: contact_margin 'max' needs equal geom margins, found {np.unique(margins)}"
                )
            # The planning model copies its parameters from this model (build_planning_model).
            margins *= 0.5
        return env

    def controls(self, model: mujoco.MjModel, state: SimState, actions: np.ndarray) -> np.ndarray:
        # The environment centres and scales normalised actions onto the ctrl ranges.
        act_mean = np.mean(model.actuator_ctrlrange, axis=1)
        act_rng = 0.5 * (model.actuator_ctrlrange[:, 1] - model.actuator_ctrlrange[:, 0])
        ctrl = act_mean + np.clip(actions, -1.0, 1.0) * act_rng
        return self._with_mocap(state, ctrl)

    def episode_success(self, goal_achieved: list[bool]) -> bool | None:
        return int(np.sum(goal_achieved)) > SUCCESS_MIN_STEPS

    def _env_quantities(self, env) -> dict[str, np.ndarray]:
        """The quantities the reward reads, taken from the real environment's data."""
        raw = env.unwrapped
        frames = self.read_frames(raw.model, raw.data)
        return self._quantities(raw.model, frames, raw.data.qpos, raw.data.qvel)

    def _batch_quantities(self, model: mujoco.MjModel, batch: RolloutBatch) -> dict[str, np.ndarray]:
        return self._quantities(model, batch.frames, self.qpos(model, batch.states), self.qvel(model, batch.states))

    def _quantities(self, model, frames, qpos, qvel) -> dict[str, np.ndarray]:
        raise NotImplementedError

    def _reward(self, q: dict[str, np.ndarray]) -> np.ndarray:
        raise NotImplementedError

    def _achieved(self, q: dict[str, np.ndarray]) -> np.ndarray:
        raise NotImplementedError

    def rewards(self, model, batch):
        return self._reward(self._batch_quantities(model, batch))

    def step_env(self, env, action):
        observation, *_ = env.step(self.env_action(action))
        q = self._env_quantities(env)
        return StepOutcome(float(self._reward(q)), bool(self._achieved(q)), observation)


class DoorOptions(AdroitOptions):
    velocity_term: Literal["observation", "qvel"] = "observation"
    """Small term of the planning cost: "qvel" is DAPG's 1e-5 ||qvel||^2 exactly as in the reward;
    "observation" is 1e-5 ||o[-30:]||^2 over the last 30 entries of DAPG's observation (hand joints,
    latch, door, palm and handle positions), as the thesis authors' implementation computed it."""


class Door(_AdroitTask):
    """Door (DAPG): press the handle to release the latch, then pull the door open.

    r = -0.1 ||palm - handle|| - 0.1 (hinge - 1.57)^2 - 1e-5 ||qvel||^2
        + 2 [hinge > 0.2] + 8 [hinge > 1.0] + 10 [hinge > 1.35];
    the goal holds while hinge >= 1.35.

    Planning cost (option ``velocity_term``): by default the velocity penalty
    is replaced by the term the thesis authors' implementation computed in its
    place, 1e-5 times the squared norm of the last 30 observation entries
    (its index picked observation entries, not velocities). The weight is
    tiny, but CEM keeps elites by rank: while the door is shut the other
    terms are equal for every sample, so this term alone decides which
    samples survive. It favours the palm near the handle and lets the hand
    explore; the true velocity penalty favours holding still, and with it
    iCEM at budget 100 does not open the sparse door at all. The published
    Door-sparse results were obtained with the observation term.
    """

    name = "door"
    env_id = "AdroitHandDoor-v1"
    Options = DoorOptions
    action_dim = 28
    colored_noise_beta = 2.5
    frames = (Frame("pos", "site", "S_handle"), Frame("pos", "site", "S_grasp"))
    per_episode_model_fields = ("body_pos",)  # reset moves the door frame
    description = "Adroit hand opens a door, DAPG dense reward (200 steps)"

    use_palm_term = True
    """Whether the reward includes -0.1 ||palm - handle|| (False: Door sparse)."""
    batch_observations = True

    def observations(self, model, batch):
        q = self._batch_quantities(model, batch)
        return self._observation(model, self.qpos(model, batch.states), q)

    def _quantities(self, model, frames, qpos, qvel):
        hinge = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, "door_hinge")
        return {
            "handle": frames[..., self.frame_slice("S_handle")],
            "palm": frames[..., self.frame_slice("S_grasp")],
            "hinge": qpos[..., model.jnt_qposadr[hinge]],
            "qvel": qvel,
        }

    def _reward(self, q):
        hinge = q["hinge"]
        reward = -0.1 * (hinge - 1.57) * (hinge - 1.57) - 1e-5 * np.sum(q["qvel"] ** 2, axis=-1)
        if self.use_palm_term:
            reward = reward - 0.1 * np.linalg.norm(q["palm"] - q["handle"], axis=-1)
        reward = reward + 2.0 * (hinge > 0.2) + 8.0 * (hinge > 1.0) + 10.0 * (hinge > 1.35)
        return reward

    def _achieved(self, q):
        return q["hinge"] >= 1.35

    def costs(self, model, batch):
        q = self._batch_quantities(model, batch)
        if self.options.velocity_term == "qvel":
            return -self._reward(q)
        velocity_penalty = 1e-5 * np.sum(q["qvel"] ** 2, axis=-1)
        tail = self._observation(model, self.qpos(model, batch.states), q)[..., -model.nv :]
        return -(self._reward(q) + velocity_penalty) + 1e-5 * np.sum(tail**2, axis=-1)

    @staticmethod
    def _observation(model, qpos, q) -> np.ndarray:
        """DAPG's door observation: hand joints, latch, door, palm, handle, palm - handle, door open (+-1)."""
        hinge = q["hinge"][..., None]
        return np.concatenate(
            [
                qpos[..., 1:-2],
                qpos[..., -1:],
                hinge,
                q["palm"],
                q["handle"],
                q["palm"] - q["handle"],
                np.where(hinge > 1.0, 1.0, -1.0),
            ],
            axis=-1,
        )


class DoorSparse(Door):
    """Door (sparse reward): Door without the palm-to-handle term.

    Nothing rewards reaching the handle, so the reward only changes once the
    door moves (section 3.3.1). Not gymnasium-robotics' binary Sparse variant.
    """

    name = "door_sparse"
    use_palm_term = False
    description = "Adroit door without the palm-to-handle term (200 steps)"


GOAL_RADIUS = 0.1
"""m: DAPG's Relocate goal holds while the ball is this close to the target."""
STEP_SECONDS = 0.01
"""Seconds per Relocate step: DAPG's frame_skip 5 of the model's 0.002 s timestep."""
FREE_FLIGHT_TOLERANCE = 0.5
"""m/s^2: a step pair whose ball acceleration is within this of gravity alone (and horizontally of 0) counts as
free flight; a resting ball (0) and a ball pushed by the hand are far outside it."""
OFF_TABLE_DROP = 0.5
"""m: a ball ending this far below the target has left the table (the target is 0.15-0.35 m above the table
top; on the table the ball ends at most 0.32 m below it, on the floor 1.1-1.3 m)."""


class RelocateOptions(AdroitOptions):
    palm_target_term: bool = False
    """Keep DAPG's -0.5 ||palm - target|| (while the ball is lifted) in the planning cost. The thesis authors'
    implementation leaves it out of its cost (the line is commented out), so the hand is pulled to the target
    only through the ball; rewards and reported returns always include it."""


class Relocate(_AdroitTask):
    """Relocate (DAPG): pick up the ball and move it to the target.

    r = -0.1 ||palm - ball|| + [ball_z > 0.04] (1 - 0.5 ||palm - target|| - 0.5 ||ball - target||)
        + 10 [||ball - target|| < 0.1] + 20 [||ball - target|| < 0.05];
    the goal holds while ||ball - target|| < 0.1.

    Planning cost (option ``palm_target_term``): by default the negative reward without the palm-to-target
    term, as the thesis authors' implementation computed it.
    """

    name = "relocate"
    Options = RelocateOptions
    env_id = "AdroitHandRelocate-v1"
    action_dim = 30
    colored_noise_beta = 3.5
    frames = (
        Frame("pos", "xbody", "Object"),
        Frame("pos", "site", "S_grasp"),
        Frame("pos", "site", "target"),
    )
    per_episode_model_fields = ("body_pos", "site_pos")  # reset moves the ball and the target
    description = "Adroit hand moves a ball to a target, DAPG reward (200 steps)"
    batch_observations = True

    def observations(self, model, batch):
        q = self._batch_quantities(model, batch)
        ball, palm, target = q["ball"], q["palm"], q["target"]
        qpos = self.qpos(model, batch.states)
        return np.concatenate([qpos[..., :-6], palm - ball, palm - target, ball - target], axis=-1)

    def _quantities(self, model, frames, qpos, qvel):
        return {
            "ball": frames[..., self.frame_slice("Object")],
            "palm": frames[..., self.frame_slice("S_grasp")],
            "target": frames[..., self.frame_slice("target")],
        }

    def _reward(self, q):
        ball, palm, target = q["ball"], q["palm"], q["target"]
        ball_to_target = np.linalg.norm(ball - target, axis=-1)
        lifted = ball[..., 2] > 0.04
        reward = -0.1 * np.linalg.norm(palm - ball, axis=-1)
        reward = reward + lifted * (1.0 - 0.5 * np.linalg.norm(palm - target, axis=-1) - 0.5 * ball_to_target)
        reward = reward + 10.0 * (ball_to_target < 0.1) + 20.0 * (ball_to_target < 0.05)
        return reward

    def _achieved(self, q):
        return np.linalg.norm(q["ball"] - q["target"], axis=-1) < GOAL_RADIUS

    def episode_metrics(self, observations):
        """How the ball got to the target: ball_flight_steps (steps in free flight, no contact), goal_flight_steps
        (goal steps with the ball in free flight: batted up rather than held), ball_off_table (0/1: the ball
        ended on the floor, out of the hand's reach). From the observation's ball - target (the last 3)."""
        ball = np.asarray(observations)[:, -3:]  # the target is fixed within an episode
        acceleration = np.diff(ball, n=2, axis=0) / STEP_SECONDS**2
        gravity_only = (np.abs(acceleration[:, 2] + 9.81) < FREE_FLIGHT_TOLERANCE) & (
            np.linalg.norm(acceleration[:, :2], axis=1) < FREE_FLIGHT_TOLERANCE
        )
        at_goal = np.linalg.norm(ball[1:-1], axis=1) < GOAL_RADIUS
        return {
            "ball_flight_steps": float(gravity_only.sum()),
            "goal_flight_steps": float((gravity_only & at_goal).sum()),
            "ball_off_table": float(ball[-1, 2] < -OFF_TABLE_DROP),
        }

    def costs(self, model, batch):
        q = self._batch_quantities(model, batch)
        costs = -self._reward(q)
        if not self.options.palm_target_term:
            lifted = q["ball"][..., 2] > 0.04
            costs = costs - lifted * 0.5 * np.linalg.norm(q["palm"] - q["target"], axis=-1)
        return costs
