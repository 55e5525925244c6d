"""The two stateful roles of neural APSP as plain classes (the service builds actors of them).

* :class:`LearnerWorker`: the policy side of an iteration. It owns the goal
  task's environment, the SAC / DDPG learner with its replay buffer and HER,
  and the generator that seeds every episode's reset. It collects episodes
  with the exploring policy, trains on them with the reward weights it is
  handed, and evaluates the deterministic policy.
* :class:`DistanceWorker`: the DistanceTrainer role. It owns the distance
  buffer D, both count sketches, d_theta and d_old (:class:`DistanceTrainer`),
  and returns versioned reward weights after every distance phase.

Between them only :class:`Episodes` and :class:`Versioned` weights travel,
once per iteration each. Both export their whole state as a
:class:`~workers.distance.state.State` (numpy arrays plus JSON) for the
trial's checkpoints; neither imports Ray or MLflow.

The seeds derive from the trial seed exactly as in
:class:`~workers.distance.loop.NeuralAPSP` (one SeedSequence spawned three
times: distance trainer, learner, episode resets), so a trial run through the
service in ``sync`` mode is the in-process loop, iteration for iteration.
"""

from __future__ import annotations

import os
import time
from typing import Any, NamedTuple

import numpy as np

from workers.distance.buffer import Episodes
from workers.distance.config import CountSettings, DistanceSettings, LearnerSettings
from workers.distance.learners import GoalLearner, default_q_clip
from workers.distance.loop import collect_episodes
from workers.distance.rewards import DistanceReward, SparseReward
from workers.distance.state import State, generator_state, part_of, restore_generator
from workers.distance.trainer import DistanceTrainer


def trial_seeds(seed: int) -> tuple[int, int, int]:
    """(distance trainer, learner, episode resets) seeds of a trial, as NeuralAPSP derives them."""
    children = np.random.SeedSequence(seed).spawn(3)
    trainer, learner, resets = (int(child.generate_state(1)[0]) for child in children)
    return trainer, learner, resets


def set_threads(threads: int) -> None:
    """torch's intra-op threads: the CPUs this worker's phase may use."""
    import torch

    torch.set_num_threads(max(1, int(threads)))


class Versioned(NamedTuple):
    """Reward weights of d_theta with the number of distance phases behind them."""

    version: int
    """1 after the first distance phase, then +1 per phase."""
    weights: State
    """:meth:`DistanceTrainer.reward_weights`: network and input statistics."""


class DistanceWorker:
    """The DistanceTrainer role: buffer D, count sketches, d_theta, d_old (Alg. 4 lines 4-20).

    Args:
        distance: DistanceSettings fields (resolved for the task and reward).
        counts: CountSettings fields.
        obs_dim, action_dim, goal_dim, horizon: the goal task's sizes.
        seed: the trial seed (the trainer's seed derives from it, see :func:`trial_seeds`).
        threads: torch threads.
    """

    def __init__(
        self,
        distance: dict[str, Any],
        counts: dict[str, Any],
        obs_dim: int,
        action_dim: int,
        goal_dim: int,
        horizon: int,
        seed: int,
        threads: int = 1,
    ):
        set_threads(threads)
        self.trainer = DistanceTrainer(
            DistanceSettings(**distance),
            CountSettings(**counts),
            obs_dim,
            action_dim,
            goal_dim,
            horizon,
            seed=trial_seeds(seed)[0],
        )
        self.version = 0

    def train(self, episodes: Episodes) -> tuple[dict[str, float], Versioned]:
        """Merge D_last into D, count, temporal phase, target copy, triangular phase; new weights."""
        start = time.perf_counter()
        self.trainer.add_episodes(episodes)
        metrics = self.trainer.train()
        self.version += 1
        metrics["time/distance_train"] = time.perf_counter() - start
        return metrics, self.weights()

    def weights(self) -> Versioned:
        """The current reward weights (after the last distance phase)."""
        return Versioned(self.version, self.trainer.reward_weights())

    def distances(self, observations: np.ndarray, actions: np.ndarray | None, goals: np.ndarray) -> np.ndarray:
        """d_theta for a batch (heat maps, diagnostics)."""
        model = self.trainer.model
        return model.function(observations, actions if model.function.uses_action else None, goals)

    def state(self) -> State:
        """The trainer's whole state and the weights version."""
        state = self.trainer.state()
        return State(state.arrays, state.meta | {"version": self.version})

    def load(self, state: State) -> None:
        self.trainer.load(state)
        self.version = int(state.meta["version"])

    def pid(self) -> int:
        return os.getpid()


class LearnerWorker:
    """The learner role: env, SAC / DDPG + HER, replay buffer, reset generator (Alg. 4 lines 3, 21-24).

    Args:
        task_name, task_options: the goal task.
        learner: LearnerSettings fields (resolved).
        reward: ``sparse`` (Sparse+HER) or ``distance`` (-d, weights from the DistanceTrainer).
        seed: the trial seed.
        threads: torch threads.
    """

    def __init__(
        self,
        task_name: str,
        task_options: dict[str, Any],
        learner: dict[str, Any],
        reward: str,
        seed: int,
        threads: int = 1,
    ):
        from workers.tasks.goal_tasks import make_goal_task

        set_threads(threads)
        self.task = make_goal_task(task_name, task_options)
        self.env = self.task.make_env()
        _, learner_seed, reset_seed = trial_seeds(seed)
        settings = LearnerSettings(**learner)
        reward_function = (
            SparseReward(self.task.is_success)
            if reward == "sparse"
            else DistanceReward(floor=0.0 if settings.nonnegative_distance else None)
        )
        q_clip = default_q_clip(reward_function.kind, settings.gamma, self.task.episode_length)
        task = self.task
        self.learner = GoalLearner(
            settings,
            task.obs_dim,
            task.action_dim,
            task.goal_dim,
            task.episode_length,
            reward_function,
            q_clip,
            seed=learner_seed,
        )
        self.rng = np.random.default_rng(reset_seed)
        self.pending: Episodes | None = None
        self.weights_version = 0

    def collect(self, count: int) -> tuple[Episodes, dict[str, float]]:
        """``count`` episodes with the exploring policy; they wait here for :meth:`train`."""
        start = time.perf_counter()
        episodes, stats = collect_episodes(
            self.task, self.env, lambda s, g: self.learner.act(s, g, explore=True), count, self.rng
        )
        self.pending = episodes if self.pending is None else Episodes.concatenate([self.pending, episodes])
        stats["time"] = time.perf_counter() - start
        return episodes, stats

    def train(self, weights: Versioned | None) -> dict[str, float]:
        """Install the reward weights (if any), store the pending episodes, run the policy phase."""
        if self.pending is None:
            raise RuntimeError("collect before train")
        start = time.perf_counter()
        if weights is not None:
            self.learner.set_reward_weights(weights.weights)
            self.weights_version = weights.version
        episodes, self.pending = self.pending, None
        self.learner.add_episodes(episodes)
        metrics = self.learner.train(episodes=len(episodes))
        metrics["learner/reward_weights_version"] = float(self.weights_version)
        metrics["time/learner_train"] = time.perf_counter() - start
        return metrics

    def evaluate(self, count: int) -> dict[str, float]:
        """``count`` episodes of the deterministic policy (stored nowhere)."""
        if count == 0:
            return {}
        start = time.perf_counter()
        _, stats = collect_episodes(
            self.task, self.env, lambda s, g: self.learner.act(s, g, explore=False), count, self.rng
        )
        stats["time"] = time.perf_counter() - start
        return stats

    def actions(self, observations: np.ndarray, goals: np.ndarray) -> np.ndarray:
        """Deterministic policy actions for a batch (heat maps)."""
        return self.learner.act(observations, goals, explore=False)

    def values(self, observations: np.ndarray, goals: np.ndarray) -> np.ndarray:
        """Q(s, pi(s, g), g) of the first critic for a batch, pi deterministic (Fig. 23 heat map)."""
        import torch

        learner = self.learner
        with torch.no_grad():
            inputs = learner.policy.inputs(observations, goals)
            actions = torch.as_tensor(learner.act(observations, goals, explore=False), dtype=torch.float32)
            return learner.critics(inputs, actions)[0].numpy().astype(np.float64)

    def state(self) -> State:
        """Learner (networks, optimisers, buffer, generators), reset generator, pending episodes."""
        learner = self.learner.state()
        arrays = {f"learner/{key}": value for key, value in learner.arrays.items()}
        meta: dict[str, Any] = {
            "learner": learner.meta,
            "rng": generator_state(self.rng),
            "weights_version": self.weights_version,
            "pending": self.pending is not None,
        }
        if self.pending is not None:
            arrays |= {f"pending/{name}": value for name, value in zip(Episodes._fields, self.pending)}
        return State(arrays, meta)

    def load(self, state: State) -> None:
        self.learner.load(part_of(state, "learner"))
        restore_generator(self.rng, state.meta["rng"])
        self.weights_version = int(state.meta["weights_version"])
        self.pending = None
        if state.meta["pending"]:
            self.pending = Episodes(*(np.array(state.arrays[f"pending/{name}"]) for name in Episodes._fields))

    def pid(self) -> int:
        return os.getpid()

    def close(self) -> None:
        self.env.close()
