"""What runs inside the service's Ray actors, as plain classes.

The scheduler turns these classes into actors with ``ray.remote``; here they
import neither Ray nor MLflow, so they are unit-tested like any other code.

* :class:`SimulationWorker` holds a task's planning model and evaluates
  batches of action sequences natively (thesis chapter 3: ground-truth
  trajectory batches of iCEM).
* :class:`TrialRunner` runs the MPC episodes of one trial: the real
  environment, the planner, and costs from whatever evaluator it is given (a
  pool of simulation workers, or an in-process evaluator).

Later stages (DAgger relabeling, ensemble training, distance-net updates)
become further classes here with their own actors.
"""

from __future__ import annotations

import os
import resource
import threading
import time
import uuid
from typing import Any, NamedTuple

import numpy as np

from workers import code_fingerprint
from workers.mpc import EpisodeResult, Evaluator, StepRecord, run_episode
from workers.planning import CEMPlanner, PlannerConfig
from workers.rollout import BatchEvaluator
from workers.tasks import SimState, make_task


class SimulationWorker:
    """Evaluates batches of action sequences of one task in native MuJoCo.

    Args:
        task_name: registry name of the task.
        threads: native rollout threads of this worker.
        task_options: the task's options (its planning cost switches).
    """

    def __init__(self, task_name: str, threads: int = 1, task_options: dict[str, Any] | None = None):
        self.task = make_task(task_name, task_options)
        env = self.task.make_env()
        env.reset(seed=0)
        model = self.task.build_planning_model(env)
        env.close()
        self.evaluator = BatchEvaluator(self.task, model, threads)
        self.incarnation = uuid.uuid4().hex
        """Changes when the worker is restarted, which lets callers count restarts."""

    def costs(self, state: SimState, actions: np.ndarray) -> tuple[np.ndarray, str]:
        """Planning costs (N,) of action sequences (N, h, d), and this worker's incarnation."""
        return self.evaluator.costs(state, actions), self.incarnation

    def pid(self) -> int:
        """Process id (for fault-injection tests and diagnostics)."""
        return os.getpid()

    def ready(self) -> str:
        return self.incarnation


def episode_seed(trial_seed: int, episode: int) -> int:
    """Seed of episode ``episode`` of a trial: the trial seed first, then derived ones."""
    if episode == 0:
        return trial_seed
    return int(np.random.SeedSequence([trial_seed, episode]).generate_state(1)[0] % 2**31)


class EpisodeReport(NamedTuple):
    """One finished episode of a trial, as sent back to the driver."""

    episode: int
    """Index of the episode within the trial."""
    seed: int
    """Seed of the episode (:func:`episode_seed`)."""
    result: EpisodeResult
    """Return, success and per-step figures of the episode."""
    episode_seconds: float
    """Wall-clock seconds of the whole episode (planning and environment steps)."""
    worker_restarts: int
    """Simulation-worker restarts observed during the episode."""


class TrialRunner:
    """Runs the MPC episodes of one trial.

    Args:
        task_name: registry name of the task.
        planner: the trial's resolved planner config.
        seed: the trial seed.
        evaluator: where planning costs come from (``costs(state, actions)``).
        max_steps: cut episodes to this many steps (default: the task's length).
        threads: rollout threads of the in-process evaluator (when ``evaluator`` is None).
        expected_code: the driver's :func:`workers.code_fingerprint`; a mismatch is refused.
        task_options: the task's options (its planning cost switches).
    """

    def __init__(
        self,
        task_name: str,
        planner: PlannerConfig,
        seed: int,
        evaluator: Evaluator | None = None,
        max_steps: int | None = None,
        threads: int = 1,
        expected_code: str | None = None,
        task_options: dict[str, Any] | None = None,
    ):
        if expected_code is not None and expected_code != code_fingerprint():
            raise RuntimeError(
                f"this node runs different icemlab code (fingerprint {code_fingerprint()}) than the driver "
                f"({expected_code}); install the same icemlab on every node (see deploy/Dockerfile)"
            )
        self.task = make_task(task_name, task_options)
        self.env = self.task.make_env()
        self.planner_config = planner
        self.seed = seed
        self.max_steps = max_steps
        self.action_dim = int(np.prod(self.env.action_space.shape))
        if evaluator is None:
            self.env.reset(seed=seed)
            evaluator = BatchEvaluator(self.task, self.task.build_planning_model(self.env), threads)
        if hasattr(evaluator, "prepare"):
            evaluator.prepare()  # start-up work is not planning time
        self.evaluator = evaluator
        self._lock = threading.Lock()
        self._progress: dict[str, Any] = {"episode": None, "step": 0, "steps": self.episode_steps}

    @property
    def episode_steps(self) -> int:
        return self.max_steps or self.task.episode_length

    def progress(self) -> dict[str, Any]:
        """Current episode and step (read concurrently with :meth:`run_episode`)."""
        with self._lock:
            return dict(self._progress)

    def run_episode(self, episode: int) -> EpisodeReport:
        """Run episode ``episode`` of the trial and report it."""
        seed = episode_seed(self.seed, episode)
        planner = CEMPlanner(self.planner_config, self.action_dim, seed=seed)
        restarts_before = getattr(self.evaluator, "restarts", 0)

        def on_step(record: StepRecord) -> None:
            with self._lock:
                self._progress = {"episode": episode, "step": record.step + 1, "steps": self.episode_steps}

        with self._lock:
            self._progress = {"episode": episode, "step": 0, "steps": self.episode_steps}
        started = time.perf_counter()
        result = run_episode(self.task, self.env, planner, self.evaluator, seed, self.episode_steps, on_step)
        return EpisodeReport(
            episode=episode,
            seed=seed,
            result=result,
            episode_seconds=time.perf_counter() - started,
            worker_restarts=getattr(self.evaluator, "restarts", 0) - restarts_before,
        )

    def pid(self) -> int:
        return os.getpid()

    def peak_memory_mb(self) -> float:
        """Peak resident memory of this process."""
        return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
