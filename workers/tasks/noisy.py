"""Noisy-HalfCheetah (thesis App. D.1.1, D.1.5, D.4, Fig. 36): aleatoric noise above a speed, a low ceiling.

The thesis describes the noise twice, differently: Gaussian noise on the
*actions* when the forward velocity exceeds 6 (D.1.1, and Fig. 36a's caption
"performance under noisy actions"; Solo8 reuses "as in the Noisy-HalfCheetah
environment, Gaussian action noise"), and noise on the *simulator state*,
s'_t = s_t + zeta_t with a diagonal covariance of 0.2 (D.4, eq. 37). Action
noise is the default here: three passages name it, and a state jump of
standard deviation 0.45 in every joint angle and velocity at every fast step
would throw the cheetah about far more than "destabilised" (D.1.2) suggests.
``noise_on="state"`` gives eq. 37.

* Noise: N(0, 0.2) per dimension, 0.2 read as the *variance* (Sigma's
  diagonal in D.4; D.1.1 writes N(mu, sigma^2)); added when the forward
  velocity qvel[0] of the state the step starts from exceeds 6. Noisy actions
  are clipped to [-1, 1] like every HalfCheetah control; state noise is added
  to qpos and qvel after the step.
* Reward: HalfCheetah-v5's forward velocity minus 0.1 |a|^2 of the action the
  *agent* chose (the noise is the environment's, not the agent's, cost).
* Ceiling (D.1.5, D.4): h = 0.3 on observation 0, the torso's height relative
  to its start (the rootz slide joint): the torso rests 0.7 above the ground,
  so an absolute 0.3 would be violated at every step. Violations are counted
  apart from the return and do not end the episode (D.4); the planning cost
  adds ``ceiling_cost`` per violating particle step ("PETS has the same
  penalty cost for hard violations", D.1.5), and RAZER's safety term uses
  :attr:`NoisyHalfCheetah.safety_boxes`.
* Episodes are 300 steps (Fig. 36's caption).

The planning cost reads the forward velocity from observation 8 (qvel[0] after
the step), where the environment's reward uses the mean velocity over the step
(x displacement / dt): the observation excludes the x position.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, Literal

import gymnasium as gym
import numpy as np
from pydantic import Field

from workers.dynamics.settings import SafetyBox
from workers.tasks.base import TaskOptions
from workers.tasks.model_based import ModelBasedTask

if TYPE_CHECKING:
    import torch

CTRL_COST_WEIGHT = 0.1
"""HalfCheetah-v5's control cost weight."""
HEIGHT_INDEX = 0
"""Observation index of the torso height (rootz) in HalfCheetah-v5."""
VELOCITY_INDEX = 8
"""Observation index of the forward velocity qvel[0] in HalfCheetah-v5."""


class NoisyHalfCheetahEnv(gym.Wrapper):
    """HalfCheetah-v5 with Gaussian noise above a forward velocity and a counted (not enforced) ceiling.

    Args:
        env: a HalfCheetah-v5 environment.
        noise_on: ``action`` (D.1.1, default) or ``state`` (eq. 37).
        noise_variance: variance of the noise per dimension (0.2 in D.4).
        velocity_threshold: noise is added when the forward velocity exceeds this (6 in D.1.1).
        ceiling: torso height (observation 0) above which a step counts as a violation (0.3 in D.4).
    """

    def __init__(
        self,
        env: gym.Env,
        noise_on: Literal["action", "state"] = "action",
        noise_variance: float = 0.2,
        velocity_threshold: float = 6.0,
        ceiling: float = 0.3,
    ):
        super().__init__(env)
        if noise_on not in ("action", "state"):
            raise ValueError(f"noise_on must be 'action' or 'state', got {noise_on!r}")
        if noise_variance < 0:
            raise ValueError(f"noise_variance must be >= 0, got {noise_variance}")
        self.noise_on, self.noise_std = noise_on, float(np.sqrt(noise_variance))
        self.velocity_threshold, self.ceiling = velocity_threshold, ceiling

    def step(self, action):
        raw = self.env.unwrapped
        clean = np.clip(np.asarray(action, dtype=np.float64), -1.0, 1.0)
        noisy = bool(raw.data.qvel[0] > self.velocity_threshold)
        applied = clean
        if noisy and self.noise_on == "action":
            applied = np.clip(clean + self.noise_std * raw.np_random.normal(size=clean.shape), -1.0, 1.0)
        obs, _reward, terminated, truncated, info = self.env.step(applied)
        if noisy and self.noise_on == "state":
            qpos = raw.data.qpos + self.noise_std * raw.np_random.normal(size=raw.model.nq)
            qvel = raw.data.qvel + self.noise_std * raw.np_random.normal(size=raw.model.nv)
            raw.set_state(qpos, qvel)
            obs = raw._get_obs()
        reward = float(info["x_velocity"] - CTRL_COST_WEIGHT * np.square(clean).sum())
        info = dict(
            info, noisy_step=noisy, applied_action=applied, ceiling_violation=bool(obs[HEIGHT_INDEX] > self.ceiling)
        )
        return obs, reward, terminated, truncated, info


class NoisyHalfCheetahOptions(TaskOptions):
    """Options of Noisy-HalfCheetah (see workers/tasks/noisy.py for the thesis's two readings)."""

    noise_on: Literal["action", "state"] = "action"
    """Where the noise goes: ``action`` (D.1.1, default) or ``state`` (eq. 37)."""
    noise_variance: float = Field(0.2, ge=0)
    """Variance of the Gaussian noise per dimension (0.2 in D.4)."""
    velocity_threshold: float = 6.0
    """Noise is added when the forward velocity exceeds this (6 in D.1.1)."""
    ceiling: float = 0.3
    """Torso height (observation 0, relative to the start) above which a step violates safety (0.3 in D.4)."""
    ceiling_cost: float = Field(0.0, ge=0)
    """Planning cost per particle step above the ceiling (PETS' hard-violation penalty, D.1.5); 0: none."""
    episode_length: int = Field(300, ge=1)
    """Environment steps per episode (300 in Fig. 36)."""


class NoisyHalfCheetah(ModelBasedTask):
    """Noisy-HalfCheetah as a chapter-5 task (see the module docstring for every choice).

    Options (:class:`NoisyHalfCheetahOptions`): noise_on, noise_variance, velocity_threshold, ceiling,
    ceiling_cost, episode_length.
    """

    Options = NoisyHalfCheetahOptions
    name = "noisy_halfcheetah"
    observation_dim = 17
    action_dim = 6
    ensemble_preset = "noisy_halfcheetah"
    colored_noise_beta = 0.25  # Table 16
    planner_defaults = {"population": 120, "iterations": 4}  # Table 16: num_simulated_trajectories, opt_iterations
    description = "HalfCheetah with Gaussian noise above velocity 6 and a ceiling at 0.3 (RAZER, App. D.4)"

    def __init__(self, **options: Any):
        super().__init__(**options)
        o = self.options
        self.noise_on, self.noise_variance = o.noise_on, o.noise_variance
        self.velocity_threshold, self.ceiling, self.ceiling_cost = o.velocity_threshold, o.ceiling, o.ceiling_cost
        self.episode_length = o.episode_length

    def make_env(self) -> gym.Env:
        env = gym.make("HalfCheetah-v5", max_episode_steps=self.episode_length)
        return NoisyHalfCheetahEnv(env, self.noise_on, self.noise_variance, self.velocity_threshold, self.ceiling)

    def planning_cost(self, obs: torch.Tensor, action: torch.Tensor, next_obs: torch.Tensor) -> torch.Tensor:
        """-(forward velocity - 0.1 |a|^2) + ceiling_cost [height > ceiling]."""
        cost = -(next_obs[:, VELOCITY_INDEX] - CTRL_COST_WEIGHT * action.square().sum(dim=-1))
        if self.ceiling_cost:
            cost = cost + self.ceiling_cost * (next_obs[:, HEIGHT_INDEX] > self.ceiling).to(cost.dtype)
        return cost

    @property
    def safety_boxes(self) -> tuple[SafetyBox, ...]:
        """The region above the ceiling (D.1.5)."""
        return (SafetyBox(dims=(HEIGHT_INDEX,), low=(self.ceiling,), high=(None,)),)

    def episode_metrics(
        self, observations: np.ndarray, rewards: np.ndarray, infos: list[dict[str, Any]]
    ) -> dict[str, float]:
        """return, ceiling_violations (= safety_violations, counted apart from the return), failure (any violation),
        noisy_steps, mean_velocity."""
        observations = np.asarray(observations)
        violations = int(np.sum(observations[1:, HEIGHT_INDEX] > self.ceiling))
        return {
            "return": float(np.sum(rewards)),
            "ceiling_violations": float(violations),
            "safety_violations": float(violations),
            "failure": float(violations > 0),
            "noisy_steps": float(sum(bool(info.get("noisy_step")) for info in infos)),
            "mean_velocity": float(observations[1:, VELOCITY_INDEX].mean()) if len(observations) > 1 else 0.0,
        }
