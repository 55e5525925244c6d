"""Episodes in a real environment, planned by iCEM on a learned ensemble (Alg. 5), and the worker that runs them.

:func:`run_model_episode` is the MPC loop of chapter 5: at every step the
planner (workers/planning/icem.py) optimises action sequences against the
RAZER cost of the ensemble (:class:`~workers.dynamics.evaluator.EnsembleEvaluator`)
from the current observation, and the first action of the best elite (Table
15) or of the mean (section 5.3.1) is executed in the real environment. The
loop records the trajectory (the training data of the next iteration), the
task's episode metrics and the means of the cost terms c, c_A, c_E, c_S of the
best sequence of each step (PlanResult.components): the executed plan's with
``best_action``; with the mean executed (``best_action: false``) the refitted
mean itself is never evaluated, so they describe the best sample beside it.

:func:`run_random_episode` is the colored-noise exploration the MBRL loop
starts from.

:class:`PlanningWorker` runs either kind for the ``mbrl`` method: a pure
function of (weights, job), so a lost worker is restarted and its episode
retried with the same result. It rebuilds the model only when the weights
version changes.
"""

from __future__ import annotations

import json
import os
import time
from typing import Any, NamedTuple

import numpy as np

from workers.data import Trajectory, TrajectoryRecorder
from workers.dynamics.settings import RazerSettings
from workers.planning import CEMPlanner, PlannerConfig
from workers.planning.icem import CostBatch
from workers.planning.noise import DEFAULT_NOISE_RELEASE, colored_noise

COST_TERMS = ("c", "c_A", "c_E", "c_S", "u_A", "u_E")
"""The cost terms of Alg. 5 line 7 whose means over the executed plans are reported, and the unweighted
uncertainty sums u_A = sum_t U(Var_A), u_E = sum_t U(Var_E) (for choosing w_A, w_E)."""

DIVERGED_COST = 1e9
"""Cost of a sequence whose predicted rollout diverged (non-finite cost): ranked last, yet the planner still
has a plan when every sequence diverged (an early, barely trained model far from its data)."""


class EpisodeJob(NamedTuple):
    """One episode for a planning worker."""

    seed: int
    """Seeds the environment reset, the planner's sampling and the particle noise."""
    razer: dict[str, Any] | None = None
    """The cost settings (a RazerSettings as a dict); None: a colored-noise random episode."""
    label: str = ""
    """What the episode is for (for progress lines)."""
    task_options: dict[str, Any] | None = None
    """Options over the worker's task options for this episode (a frozen row's ``frozen.task_options``, e.g. a
    longer episode); None: the worker's own task."""


class EpisodeOutcome(NamedTuple):
    """A finished episode."""

    trajectory: Trajectory
    """Observations, actions (normalised) and rewards."""
    metrics: dict[str, float]
    """The task's episode metrics (return, success, falls, ...), ``steps``, planning_seconds_per_step and the
    means of the cost terms over the executed plans as cost/c, cost/c_A, cost/c_E, cost/c_S, and
    diverged_fraction, the share of evaluated sequences whose predicted rollout diverged (planned episodes)."""
    weights_version: int | None
    """Version of the weights the episode was planned with (None: random episode)."""


def run_random_episode(
    task, env, seed: int, beta: float, scale: float = 1.0, release: str = DEFAULT_NOISE_RELEASE
) -> EpisodeOutcome:
    """An episode of colored-noise actions (exponent ``beta``, std ``scale``, clipped to [-1, 1]), drawn as the
    colorednoise ``release`` the planner follows does (workers/planning/noise.py)."""
    rng = np.random.default_rng(seed)
    noise = colored_noise(beta, (1, task.action_dim, task.episode_length), rng, release)[0].T  # (T, d)
    actions = np.clip(scale * noise, -1.0, 1.0)
    observation, _ = env.reset(seed=seed)
    recorder = TrajectoryRecorder(np.asarray(observation, dtype=np.float64))
    infos = []
    for action in actions:
        observation, reward, terminated, truncated, info = env.step(task.env_action(action))
        recorder.add(action, reward, observation)
        infos.append(info)
        if terminated or truncated:
            break
    trajectory = recorder.finish()
    metrics = task.episode_metrics(trajectory.observations, trajectory.rewards, infos)
    metrics["steps"] = float(len(trajectory))
    return EpisodeOutcome(trajectory, metrics, None)


def run_model_episode(
    task,
    env,
    model,
    planner_config: PlannerConfig,
    razer: RazerSettings,
    particles: int,
    seed: int,
    on_step=None,
) -> EpisodeOutcome:
    """One MPC episode of ``task`` in ``env`` planned on the ensemble ``model`` (Alg. 5)."""
    from workers.dynamics.evaluator import EnsembleEvaluator

    evaluator = EnsembleEvaluator(
        model, task.planning_cost, razer, particles=particles, seed=seed, project=task.project_states
    )
    planner = CEMPlanner(planner_config, task.action_dim, seed=seed)
    observation, _ = env.reset(seed=seed)
    observation = np.asarray(observation, dtype=np.float64)
    recorder = TrajectoryRecorder(observation)
    infos: list[dict[str, Any]] = []
    terms: dict[str, list[float]] = {name: [] for name in COST_TERMS}
    seconds = []
    diverged = [0, 0]  # sequences with a non-finite cost, sequences evaluated

    for t in range(task.episode_length):

        def cost_function(actions: np.ndarray, start: np.ndarray = observation) -> CostBatch:
            total, components = evaluator.costs(start, actions)
            bad = ~np.isfinite(total)
            diverged[0] += int(bad.sum())
            diverged[1] += len(total)
            if bad.any():
                total = np.where(bad, DIVERGED_COST, total)
                components = {k: np.where(np.isfinite(v), v, 0.0) for k, v in components.items()}
            return CostBatch(total, "mean", components)

        started = time.perf_counter()
        result = planner.plan(cost_function)
        seconds.append(time.perf_counter() - started)
        for name in COST_TERMS:
            if name in result.components:
                terms[name].append(result.components[name])
        observation, reward, terminated, truncated, info = env.step(task.env_action(result.action))
        observation = np.asarray(observation, dtype=np.float64)
        recorder.add(result.action, reward, observation)
        infos.append(info)
        if on_step is not None:
            on_step(t + 1, task.episode_length)
        if terminated or truncated:
            break

    trajectory = recorder.finish()
    metrics = task.episode_metrics(trajectory.observations, trajectory.rewards, infos)
    metrics["steps"] = float(len(trajectory))
    metrics["planning_seconds_per_step"] = float(np.mean(seconds))
    metrics["diverged_fraction"] = diverged[0] / max(diverged[1], 1)
    if razer.safety_boxes and "safety_violations" not in metrics:
        metrics["safety_violations"] = float(count_in_boxes(trajectory.observations[1:], razer))
    metrics |= {f"cost/{name}": float(np.mean(values)) for name, values in terms.items() if values}
    return EpisodeOutcome(trajectory, metrics, model.weights_version)


def count_in_boxes(observations: np.ndarray, razer: RazerSettings) -> int:
    """Steps whose observation lies inside any of the settings' safety boxes (the exact, not the predicted, set)."""
    inside = np.zeros(len(observations), dtype=bool)
    for box in razer.safety_boxes:
        hit = np.ones(len(observations), dtype=bool)
        for dim, low, high in zip(box.dims, box.low, box.high):
            values = observations[:, dim]
            hit &= (values >= (-np.inf if low is None else low)) & (values <= (np.inf if high is None else high))
        inside |= hit
    return int(inside.sum())


class PlanningWorker:
    """Runs episodes of the ``mbrl`` method in its own real environment: random or planned on given weights.

    Args:
        task_name: registry name of a chapter-5 task.
        task_options: the task's options.
        planner: a resolved PlannerConfig as a dict.
        particles: PETSUS particles per sequence.
        random_beta: colored-noise exponent of random episodes (drawn as the planner's ``noise_release``).
        random_scale: standard deviation of random episodes' actions before clipping.
        cpus: CPUs this worker holds; torch uses as many threads.
    """

    def __init__(
        self,
        task_name: str,
        task_options: dict[str, Any],
        planner: dict[str, Any],
        particles: int,
        random_beta: float,
        random_scale: float = 1.0,
        cpus: float = 1,
    ):
        import torch

        from workers.tasks import make_task

        self.threads = max(1, int(cpus))
        torch.set_num_threads(self.threads)
        self.task_name, self.task_options = task_name, dict(task_options)
        self.task = make_task(task_name, task_options)
        self.env = self.task.make_env()
        self._variants: dict[str, tuple[Any, Any]] = {}
        """Task and environment per set of options that differ from the worker's own (frozen rows)."""
        self.planner_config = PlannerConfig(**planner)
        self.particles = particles
        self.random_beta, self.random_scale = random_beta, random_scale
        self._model = None
        self._model_key: tuple | None = None

    def model(self, weights):
        """The ensemble of ``weights``, rebuilt only when the version changes."""
        key = (weights.version, weights.meta.get("seed"))  # a trial's versions name its weights uniquely
        if self._model is None or key != self._model_key:
            self._model = weights.model()
            self._model_key = key
        return self._model

    def run_episode(self, weights, job: EpisodeJob, on_step=None) -> EpisodeOutcome:
        """Run ``job``: a colored-noise episode (``job.razer`` None) or one planned on ``weights``."""
        import torch

        torch.set_num_threads(self.threads)  # a host process (the runner) may have set its own count since
        task, env = self.task_and_env(job.task_options)
        if job.razer is None:
            release = self.planner_config.noise_release
            return run_random_episode(task, env, job.seed, self.random_beta, self.random_scale, release)
        razer = RazerSettings(**job.razer)
        return run_model_episode(
            task, env, self.model(weights), self.planner_config, razer, self.particles, job.seed, on_step
        )

    def task_and_env(self, options: dict[str, Any] | None):
        """The worker's task and environment, or, for ``options`` that differ, ones built with them (kept)."""
        if not options:
            return self.task, self.env
        key = json.dumps(options, sort_keys=True)
        if key not in self._variants:
            from workers.tasks import make_task

            task = make_task(self.task_name, self.task_options | options)
            self._variants[key] = (task, task.make_env())
        return self._variants[key]

    def pid(self) -> int:
        return os.getpid()

    def close(self) -> None:
        self.env.close()
        for _, env in self._variants.values():
            env.close()
