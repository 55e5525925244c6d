"""A tiny, fast task for tests and smoke runs: a point mass reaching a goal.

Not a thesis task. It exercises every part of the engine that the thesis
tasks need (a goal kept in Python like Fetch's, a reward that reads a site
position as the environment sees it after a step) at a tiny fraction of their
cost, so tests and the quickstart sweep run in seconds.
"""

from __future__ import annotations

from pathlib import Path

import gymnasium as gym
import mujoco
import numpy as np
from gymnasium.envs.mujoco import MujocoEnv
from gymnasium.spaces import Box

from workers.tasks.base import Frame, GroundTruthTask

ENV_ID = "icemlab/PointReach-v0"
MODEL_PATH = Path(__file__).parent / "assets" / "point_reach.xml"


class PointReachEnv(MujocoEnv):
    """Point mass on a plane (two slide joints, two motors); reward -||tip - goal|| - 0.01 ||a||^2."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": 50}
    ctrl_cost_weight = 0.01
    goal_range = 0.3

    def __init__(self, **kwargs):
        observation_space = Box(-np.inf, np.inf, shape=(6,), dtype=np.float64)
        super().__init__(str(MODEL_PATH), frame_skip=2, observation_space=observation_space, **kwargs)
        self._tip = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_SITE, "tip")
        self.goal = np.zeros(3)

    def _get_obs(self) -> np.ndarray:
        return np.concatenate([self.data.qpos, self.data.qvel, (self.goal - self.data.site_xpos[self._tip])[:2]])

    def step(self, action):
        self.do_simulation(action, self.frame_skip)
        tip = self.data.site_xpos[self._tip]
        reward = -np.linalg.norm(tip - self.goal) - self.ctrl_cost_weight * np.square(action).sum()
        return self._get_obs(), float(reward), False, False, {}

    def reset_model(self) -> np.ndarray:
        qpos = self.init_qpos + self.np_random.uniform(-0.1, 0.1, self.model.nq)
        self.goal = np.array([*self.np_random.uniform(-self.goal_range, self.goal_range, 2), 0.02])
        self.set_state(qpos, np.zeros(self.model.nv))
        return self._get_obs()


if ENV_ID not in gym.registry:
    gym.register(ENV_ID, entry_point=PointReachEnv, max_episode_steps=50)


class PointReach(GroundTruthTask):
    """The tiny task: a point mass pushed to a random goal (50 steps)."""

    name = "point_reach"
    env_id = ENV_ID
    episode_length = 50
    frame_skip = 2
    action_dim = 2
    colored_noise_beta = 1.0
    frames = (Frame("pos", "site", "tip"),)
    description = "tiny point mass reaching a goal, for tests and smoke runs (50 steps)"
    batch_observations = True

    def observations(self, model, batch):
        tip = batch.frames[..., self.frame_slice("tip")]
        offset = (np.broadcast_to(batch.goal, tip.shape) - tip)[..., :2]
        return np.concatenate([self.qpos(model, batch.states), self.qvel(model, batch.states), offset], axis=-1)

    def _goal(self, env: gym.Env) -> np.ndarray:
        return env.unwrapped.goal.copy()

    def controls(self, model, state, actions):
        return self._with_mocap(state, actions)

    def rewards(self, model, batch):
        distance = np.linalg.norm(batch.frames[..., self.frame_slice("tip")] - batch.goal, axis=-1)
        return -distance - PointReachEnv.ctrl_cost_weight * np.square(batch.actions).sum(axis=-1)
