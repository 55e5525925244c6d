"""Noisy-FetchPickAndPlace (thesis section 5.4, App. D.4, Fig. 19b): gripper action noise over most of the path.

The thesis's description and what is ours where it is silent:

* **Layout.** "Starting and target positions are at the opposite sides of the
  table": the box starts near one end of the table's long (y) axis and the
  target lies above the other end. D.4 gives the box centred at y = -1.5, the
  target at y = 2.0 and noise until y = 1.67, in a frame that is not Fetch's;
  only the proportions carry over. Ours (the table spans x 1.05-1.55, y
  0.40-1.10, its top at z 0.40): box x in [1.25, 1.43], y in [0.52, 0.58]
  (centre 0.55); target x in [1.25, 1.43], y in [0.92, 0.98] (centre 0.95),
  0.10-0.20 above the box's resting height, always in the air: the thesis's
  RAZER "lifts it only in the area without action noise", so the target must
  need a lift, and the straight line from box to target ("the shortest
  path is to lift the box") then rises from the start.
* **Noisy zone.** The gripper is noisy while the grip site's y is below
  y_box + (1.67 + 1.5) / 3.5 (y_target - y_box) with the range centres,
  0.55 + 0.906 x 0.40 = 0.912 (option ``noisy_fraction``). The *gripper*
  decides, not the box: the noise is a fault of the gripper's actuation
  ("the gripper state is noisy until y = 1.67"), the gripper's position is
  what both the real environment and a simulated particle know at the start
  of a step (the stale grip-site frame of workers/tasks/base.py), and while
  the box is carried the two coincide.
* **Noise.** xi ~ N(``noise_mean``, ``noise_std``^2) is added to the gripper
  component a[3] of the chosen action at every step that starts in the zone,
  before the action is clipped to [-1, 1]. Fetch's fingers are position
  servos whose target is the current finger position plus a[3], so a
  positive a[3] + xi opens the grip with a force proportional to it (D.4).
  Holding the box with a[3] = -1, the grip opens when xi > ~1; the default
  N(0, 1) does so at about 16% of the steps, so a box carried through the
  zone (some 8-10 steps) falls with high probability, while a box slid along
  the table only stops for a step ("considerable noise", section 5.4.2; a
  planner that averages its particles still lifts early).
* **Independent draws, same process.** :meth:`NoisyFetchPickPlace.noisy_actions`
  is the one noise process: the real environment's wrapper calls it with
  draws of its own, and the planner's simulators with theirs
  (workers/dynamics/ground_truth.py). The real environment draws from a
  generator keyed by the episode's goal and the simulation time, so the draw
  of a step is a function of the captured state: a restored state repeats the
  following steps exactly and a resumed MPC episode is the one that would
  have run uninterrupted.
* **Cost and success** are chapter 3's (workers/tasks/fetch.py): reward
  -||box - target||, success when the box ends within 0.05 of the target.
* **Drops.** A box counts as dropped when it was lifted (its centre more than
  0.02 above its resting height; a box tipped onto an edge rises 0.01 at most)
  and then lies on the table again (within 0.01 of its resting height, or
  below: off the table) more than 0.05 from the target horizontally. A box
  put down deliberately away from the target counts as well; the cost never
  rewards that. ``box_drops`` of an episode is 1 if the box was dropped at
  least once (the drop rate of Fig. 19b is its mean), ``box_drop_count`` the
  number of drops.
"""

from __future__ import annotations

from typing import Any, ClassVar

import gymnasium as gym
import numpy as np
from pydantic import Field

from workers.tasks.base import TaskOptions, register_robotics_envs
from workers.tasks.fetch import GRIP_SITE, FetchPickPlaceSparse

BOX_X, BOX_Y = (1.25, 1.43), (0.52, 0.58)
"""Ranges of the box's start on the table (x along the arm, y along the table's long side)."""
TARGET_X, TARGET_Y = (1.25, 1.43), (0.92, 0.98)
"""Ranges of the target's horizontal position, on the far side of the table."""
TARGET_HEIGHT = (0.10, 0.20)
"""Range of the target's height above the box's resting height."""
PATH_START, PATH_END = float(np.mean(BOX_Y)), float(np.mean(TARGET_Y))
"""y of the range centres: the box's start (the thesis's -1.5) and the target (2.0)."""
THESIS_NOISY_FRACTION = (1.67 + 1.5) / 3.5
"""Share of the box-to-target path over which the gripper is noisy (D.4: noisy until y = 1.67 of -1.5 .. 2.0)."""

LIFT_MARGIN = 0.02
"""Height above rest beyond which the box is lifted (tipping onto an edge raises its centre 0.0104)."""
TABLE_MARGIN = 0.01
"""Height above rest within which the box lies on the table again."""
TARGET_RADIUS = 0.05
"""A box that comes down within this horizontal distance of the target was put there, not dropped."""

ENV_ID = "icemlab/NoisyFetchPickAndPlace-v0"
ENV_STREAM = 0x4E46
"""Tags the real environment's noise generator (the planners' draws use other streams)."""

# Layout of the flat observation (FetchPickPlaceSparse.observations): grip_pos, object_pos, ..., desired goal.
GRIP_POS, BOX_POS, GOAL = slice(0, 3), slice(3, 6), slice(25, 28)


def _env_class():
    """The environment, defined lazily so that importing this module does not import gymnasium_robotics."""
    register_robotics_envs()
    from gymnasium_robotics.envs.fetch.pick_and_place import MujocoFetchPickAndPlaceEnv

    class FarSidesPickAndPlaceEnv(MujocoFetchPickAndPlaceEnv):
        """FetchPickAndPlace-v4 (dense reward), the box on the near end of the table, the target above the far end."""

        def _reset_sim(self):
            super()._reset_sim()
            qpos = self._utils.get_joint_qpos(self.model, self.data, "object0:joint").copy()
            qpos[:2] = self.np_random.uniform((BOX_X[0], BOX_Y[0]), (BOX_X[1], BOX_Y[1]))
            self._utils.set_joint_qpos(self.model, self.data, "object0:joint", qpos)
            self._mujoco.mj_forward(self.model, self.data)
            return True

        def _sample_goal(self):
            low = (TARGET_X[0], TARGET_Y[0], self.height_offset + TARGET_HEIGHT[0])
            high = (TARGET_X[1], TARGET_Y[1], self.height_offset + TARGET_HEIGHT[1])
            return self.np_random.uniform(low, high)

    return FarSidesPickAndPlaceEnv


def _make_env(**kwargs) -> gym.Env:
    return _env_class()(reward_type="dense", **kwargs)


if ENV_ID not in gym.registry:
    gym.register(ENV_ID, entry_point=_make_env, max_episode_steps=50)


def env_draws(goal: np.ndarray, time: float, size: int) -> np.ndarray:
    """The real environment's standard-normal draws for the step that starts at ``time`` of the episode of ``goal``."""
    key = np.concatenate([np.ravel(goal), [time]]).astype(np.float64)
    words = np.frombuffer(key.tobytes(), dtype=np.uint32).tolist()
    return np.random.default_rng([ENV_STREAM, *words]).standard_normal(size)


class GripperNoise(gym.Wrapper):
    """The real environment's side of the noise: each step's action goes through the task's noise process.

    The step's info gains ``noisy_step`` (the step started in the noisy zone) and ``noise_draws`` (the
    standard-normal draws it used).
    """

    def __init__(self, env: gym.Env, task: NoisyFetchPickPlace):
        super().__init__(env)
        self.task = task

    def step(self, action):
        raw = self.env.unwrapped
        frames = self.task.read_frames(raw.model, raw.data)[None]
        draws = env_draws(raw.goal, float(raw.data.time), self.task.noise_dim)[None]
        chosen = np.asarray(action, dtype=np.float64)[None]
        applied = self.task.noisy_actions(chosen, frames, draws)[0]
        observation, reward, terminated, truncated, info = self.env.step(applied)
        noisy = bool(self.task.in_zone(frames)[0])
        return observation, reward, terminated, truncated, dict(info, noisy_step=noisy, noise_draws=draws[0])


class NoisyFetchPickPlaceOptions(TaskOptions):
    """Options of Noisy-FetchPickAndPlace (see workers/tasks/noisy_fetch.py for every choice)."""

    noise_mean: float = 0.0
    """Mean mu of the gripper noise xi ~ N(mu, std^2) (D.4 gives no value)."""
    noise_std: float = Field(1.0, ge=0)
    """Standard deviation of the gripper noise; at 1.0 a grip held with a[3] = -1 opens at ~16% of noisy steps."""
    noisy_fraction: float = Field(THESIS_NOISY_FRACTION, ge=0, le=1)
    """Share of the box-to-target path (range centres, along y) over which the gripper is noisy (D.4: 0.906)."""


class NoisyFetchPickPlace(FetchPickPlaceSparse):
    """Fetch Pick&Place with gripper noise over the first 0.906 of the path (see the module docstring)."""

    Options = NoisyFetchPickPlaceOptions
    options: NoisyFetchPickPlaceOptions
    name = "noisy_fetch_pick_place"
    env_id = ENV_ID
    description = (
        "Fetch carries a box across the table to a target in the air; gripper action noise until 0.906 of "
        "the way (RAZER, Fig. 19b); reward -||box-target||, success, box_drops (50 steps)"
    )
    noise_dim = 1
    observation_dim = 28
    uncertainty_dims: ClassVar[tuple[int, ...]] = (3, 4, 5)
    """The box's position: what a drop scatters (the gripper's own state is noisy wherever it is in the zone)."""

    def __init__(self, **options: Any):
        super().__init__(**options)
        self.zone_end = PATH_START + self.options.noisy_fraction * (PATH_END - PATH_START)
        """y below which the gripper is noisy."""

    def make_env(self) -> gym.Env:
        return GripperNoise(super().make_env(), self)

    def in_zone(self, frames: np.ndarray) -> np.ndarray:
        """(N,) whether steps that start at stale frames (N, nframes) are noisy: the grip site's y below the zone."""
        return frames[:, self.frame_slice(GRIP_SITE)][:, 1] < self.zone_end

    def noisy_actions(self, actions_t, frames, draws_t):
        noise = self.options.noise_mean + self.options.noise_std * draws_t[:, 0]
        applied = np.array(actions_t, dtype=np.float64)
        applied[:, 3] += np.where(self.in_zone(frames), noise, 0.0)
        return applied

    def episode_metrics(self, observations):
        """box_drops (0/1), box_drop_count, box_lifted (0/1), noisy_steps, lifted_noisy_steps (steps that start
        with the box lifted in the noisy zone)."""
        observations = np.asarray(observations)
        box, grip = observations[:, BOX_POS], observations[:, GRIP_POS]
        drops = count_box_drops(box, observations[0, GOAL], rest_height=box[0, 2])
        lifted = box[:, 2] > box[0, 2] + LIFT_MARGIN
        noisy = grip[:-1, 1] < self.zone_end
        return {
            "box_drops": float(drops > 0),
            "box_drop_count": float(drops),
            "box_lifted": float(lifted.any()),
            "noisy_steps": float(noisy.sum()),
            "lifted_noisy_steps": float((noisy & lifted[:-1]).sum()),
        }


def count_box_drops(box: np.ndarray, target: np.ndarray, rest_height: float) -> int:
    """Drops in a (T, 3) box trajectory: lifted above ``rest_height`` + 0.02, then back on the table (within
    0.01 of the rest height, or below it) more than 0.05 from ``target`` horizontally."""
    box = np.asarray(box, dtype=np.float64)
    drops, lifted = 0, False
    for position in box:
        if position[2] > rest_height + LIFT_MARGIN:
            lifted = True
        elif lifted and position[2] <= rest_height + TABLE_MARGIN:
            lifted = False
            if np.linalg.norm(position[:2] - np.asarray(target)[:2]) > TARGET_RADIUS:
                drops += 1
    return drops
