"""One in-process training loop of neural APSP and its baselines (Alg. 4), in separable phases.

An iteration is

1. **collect** n episodes with the current exploring policy (:func:`collect_episodes`);
2. **distance phase** (:func:`distance_phase`, a :class:`DistanceTrainer`): merge the episodes into D,
   update the count models, temporal updates, copy d_old, triangular updates; returns the new
   reward weights;
3. **policy phase** (:func:`policy_phase`, a :class:`GoalLearner`): install the reward weights, store the
   episodes, 100 updates per collected episode;
4. **evaluate** with the deterministic policy.

The phases only exchange :class:`Episodes` and :class:`State` weights (plain
arrays), once per iteration, so the service can run the distance phase on a
DistanceTrainer actor and the policy phase on a learner actor.
:class:`NeuralAPSP` runs all of them in one process, and exports / imports
every part (networks, optimisers, sketches, buffers, generators) as arrays
plus JSON.

Methods (section 6.6): ``sparse_her`` (no distance; sparse reward),
``ddl_her`` (d(s, g) by on-policy temporal regression), ``offpolicy_ddl_her``
(d(s, a, g), temporal loss eq. 31a only), ``ours_her`` (both losses).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

import gymnasium as gym
import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from workers.distance.buffer import Episodes
from workers.distance.config import (
    CountSettings,
    DistanceSettings,
    LearnerSettings,
    Method,
    MethodSettings,
    method_settings,
)
from workers.distance.learners import GoalLearner, default_q_clip
from workers.distance.rewards import DistanceReward, SparseReward
from workers.distance.state import State, generator_state, part_of, restore_generator
from workers.distance.trainer import DistanceTrainer
from workers.tasks.goal_tasks import GoalTask, make_goal_task

Actor = Callable[[np.ndarray, np.ndarray], np.ndarray]
"""(observation, goal) -> action in [-1, 1]."""


class LoopSettings(BaseModel):
    """A neural-APSP run: method, task, schedule, seed, and overrides of the thesis defaults."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False, frozen=True, use_attribute_docstrings=True)

    method: Method = "ours_her"
    """sparse_her, ddl_her, offpolicy_ddl_her or ours_her (section 6.6)."""
    task: str = "fetch_reach"
    """A goal task (workers.tasks.goal_tasks.GOAL_TASKS)."""
    task_options: dict[str, Any] = Field(default_factory=dict)
    """Options of the task (e.g. action_repeat for point_maze)."""
    episodes_per_iteration: int = Field(2, ge=1)
    """Episodes collected per iteration (not in the thesis; OpenAI baselines collects 2 per cycle)."""
    eval_episodes: int = Field(10, ge=0)
    """Deterministic evaluation episodes after every iteration."""
    seed: int = 0
    """Every random draw of the run derives from it (networks, hashes, sampling, env resets)."""
    counts: dict[str, Any] = Field(default_factory=dict)
    """Overrides of CountSettings over the thesis values for the task (Table 20)."""
    distance: dict[str, Any] = Field(default_factory=dict)
    """Overrides of DistanceSettings over the method's thesis values (Table 20)."""
    learner: dict[str, Any] = Field(default_factory=dict)
    """Overrides of LearnerSettings over the thesis values (Table 19)."""

    def resolved(self) -> MethodSettings:
        """Thesis defaults of the method on the task with the overrides applied (all validated)."""
        defaults = method_settings(self.method, self.task)
        if defaults.distance is None and self.distance:
            raise ValueError(f"{self.method} has no distance network; remove the distance overrides")
        distance = DistanceSettings(**(defaults.distance.model_dump() | self.distance)) if defaults.distance else None
        return MethodSettings(
            method=self.method,
            counts=CountSettings(**(defaults.counts.model_dump() | self.counts)),
            distance=distance,
            learner=LearnerSettings(**(defaults.learner.model_dump() | self.learner)),
        )


# ------------------------------------------------------------------- phases
def collect_episodes(
    task: GoalTask, env: gym.Env, act: Actor, count: int, rng: np.random.Generator
) -> tuple[Episodes, dict[str, float]]:
    """Run ``count`` full episodes; every reset is seeded from ``rng``, so the env carries no hidden state.

    Returns the episodes and success statistics: success at the last step
    (the thesis's success rate), at any step, the env's own success flag at
    the last step (Pick&Place: the box alone), the final goal distance, and
    the maximum reward: the episode's largest -||ag(s_t) - g|| (t >= 1), the
    quantity Fig. 22 and 24 plot against the threshold -0.05.
    """
    horizon = task.episode_length
    observations = np.zeros((count, horizon + 1, task.obs_dim))
    actions = np.zeros((count, horizon, task.action_dim))
    achieved = np.zeros((count, horizon + 1, task.goal_dim))
    goals = np.zeros((count, task.goal_dim))
    successes = np.zeros((count, horizon))
    env_success = np.zeros(count)
    for e in range(count):
        observation, _ = env.reset(seed=int(rng.integers(2**31)))
        observations[e, 0], achieved[e, 0], goals[e] = task.split(observation)
        for t in range(horizon):
            action = np.clip(act(observations[e, t], goals[e]), -1.0, 1.0)
            actions[e, t] = action
            observation, _, terminated, _, info = env.step(task.env_action(action))
            if terminated:
                raise RuntimeError(f"{task.name} terminated at step {t}; goal tasks need fixed-length episodes")
            observations[e, t + 1], achieved[e, t + 1], _ = task.split(observation)
        successes[e] = task.is_success(achieved[e, 1:], goals[e])
        env_success[e] = float(info.get("is_success", info.get("success", np.nan)))
    episodes = Episodes(observations, actions, achieved, goals, successes)
    stats = {
        "success": float(successes[:, -1].mean()),
        "success_any": float(successes.max(axis=1).mean()),
        "env_success": float(np.nanmean(env_success)) if not np.isnan(env_success).all() else float("nan"),
        "final_goal_distance": float(task.goal_distance(achieved[:, -1], goals).mean()),
        "max_reward": float((-task.goal_distance(achieved[:, 1:], goals[:, None])).max(axis=1).mean()),
    }
    stats |= task.evaluation_metrics(achieved[:, -1], goals)
    return episodes, stats


def distance_phase(trainer: DistanceTrainer, episodes: Episodes) -> tuple[dict[str, float], State]:
    """Merge, count, train (Alg. 4 lines 4-20); returns metrics and the reward weights for the learner."""
    trainer.add_episodes(episodes)
    metrics = trainer.train()
    return metrics, trainer.reward_weights()


def policy_phase(learner: GoalLearner, episodes: Episodes, reward_weights: State | None) -> dict[str, float]:
    """Install the reward weights, store the episodes, updates_per_episode x len(episodes) updates."""
    if reward_weights is not None:
        learner.set_reward_weights(reward_weights)
    learner.add_episodes(episodes)
    return learner.train(episodes=len(episodes))


def _prefixed(prefix: str, values: dict[str, float]) -> dict[str, float]:
    return {f"{prefix}/{key}": value for key, value in values.items()}


class NeuralAPSP:
    """The whole loop of one method on one task, in one process.

    Args:
        settings: the run's settings.
        task: an already built task (default: from ``settings.task``).
    """

    def __init__(self, settings: LoopSettings, task: GoalTask | None = None):
        self.settings = settings
        self.method = settings.resolved()
        self.task = task or make_goal_task(settings.task, settings.task_options)
        self.env = self.task.make_env()
        task = self.task
        seeds = [int(s.generate_state(1)[0]) for s in np.random.SeedSequence(settings.seed).spawn(3)]
        dims = (task.obs_dim, task.action_dim, task.goal_dim)
        self.trainer: DistanceTrainer | None = None
        if self.method.distance is not None:
            self.trainer = DistanceTrainer(
                self.method.distance, self.method.counts, *dims, task.episode_length, seed=seeds[0]
            )
            reward: SparseReward | DistanceReward = DistanceReward(
                floor=0.0 if self.method.learner.nonnegative_distance else None
            )
        else:
            reward = SparseReward(task.is_success)
        learner_settings = self.method.learner
        q_clip = default_q_clip(reward.kind, learner_settings.gamma, task.episode_length)
        self.learner = GoalLearner(learner_settings, *dims, task.episode_length, reward, q_clip, seed=seeds[1])
        self.rng = np.random.default_rng(seeds[2])
        self.iterations = 0
        self.episodes_collected = 0

    def collect(self, count: int | None = None) -> tuple[Episodes, dict[str, float]]:
        """Exploring episodes with the current policy."""
        count = count or self.settings.episodes_per_iteration
        episodes, stats = collect_episodes(
            self.task, self.env, lambda s, g: self.learner.act(s, g, explore=True), count, self.rng
        )
        self.episodes_collected += count
        return episodes, stats

    def evaluate(self, count: int | None = None) -> dict[str, float]:
        """Deterministic-policy episodes (not stored anywhere)."""
        count = self.settings.eval_episodes if count is None else count
        if count == 0:
            return {}
        _, stats = collect_episodes(
            self.task, self.env, lambda s, g: self.learner.act(s, g, explore=False), count, self.rng
        )
        return stats

    def iteration(self) -> dict[str, float]:
        """Collect, distance phase, policy phase, evaluate; returns every metric with its phase's prefix."""
        metrics: dict[str, float] = {}
        start = time.perf_counter()
        episodes, stats = self.collect()
        metrics |= _prefixed("collect", stats)
        metrics["time/collect"] = time.perf_counter() - start
        start = time.perf_counter()
        weights = None
        if self.trainer is not None:
            distance_metrics, weights = distance_phase(self.trainer, episodes)
            metrics |= distance_metrics
        metrics["time/distance"] = time.perf_counter() - start
        start = time.perf_counter()
        metrics |= policy_phase(self.learner, episodes, weights)
        metrics["time/learner"] = time.perf_counter() - start
        start = time.perf_counter()
        metrics |= _prefixed("eval", self.evaluate())
        metrics["time/eval"] = time.perf_counter() - start
        self.iterations += 1
        metrics["iteration"] = float(self.iterations)
        metrics["episodes"] = float(self.episodes_collected)
        return metrics

    def run(
        self, iterations: int, callback: Callable[[dict[str, float]], None] | None = None
    ) -> list[dict[str, float]]:
        """Several iterations; ``callback`` sees each iteration's metrics."""
        history = []
        for _ in range(iterations):
            metrics = self.iteration()
            history.append(metrics)
            if callback is not None:
                callback(metrics)
        return history

    def state(self) -> State:
        """Every part: learner, distance trainer, loop generator and counters."""
        parts = {"learner": self.learner.state()}
        if self.trainer is not None:
            parts["trainer"] = self.trainer.state()
        arrays = {f"{name}/{k}": v for name, part in parts.items() for k, v in part.arrays.items()}
        meta: dict[str, Any] = {name: part.meta for name, part in parts.items()}
        meta |= {
            "settings": self.settings.model_dump(mode="json"),
            "rng": generator_state(self.rng),
            "iterations": self.iterations,
            "episodes_collected": self.episodes_collected,
        }
        return State(arrays, meta)

    def load(self, state: State) -> None:
        """Restore :meth:`state` into a loop built with the same settings."""
        if state.meta["settings"] != self.settings.model_dump(mode="json"):
            raise ValueError("the state was saved by a loop with other settings")

        def part(name: str) -> State:
            return part_of(state, name)

        self.learner.load(part("learner"))
        if self.trainer is not None:
            self.trainer.load(part("trainer"))
            if self.trainer.recent is not None:
                self.learner.set_reward_weights(self.trainer.reward_weights())
        restore_generator(self.rng, state.meta["rng"])
        self.iterations = int(state.meta["iterations"])
        self.episodes_collected = int(state.meta["episodes_collected"])

    def close(self) -> None:
        self.env.close()
