"""The RelabelWorker: the stateless role that runs APEX's expert, policy and relabeling work.

Every call is a pure function of its arguments (seed, policy weights,
settings, states): a call retried on a restarted worker returns the same
result, so the service restarts a lost worker and retries its call without
losing or duplicating anything. A worker holds its task's real environment
(expert and policy episodes), a second one (the policy's closed-loop
rollouts and the observation replay), the planning model and a batch
evaluator with ``threads`` native rollout threads.
"""

from __future__ import annotations

import os
from typing import Any

import numpy as np

from workers.policy.expert import (
    ExpertEpisode,
    ExpertSettings,
    ICemPi,
    PolicyEpisode,
    RelabeledChunk,
    relabel_states,
    run_expert_episode,
    run_policy_episode,
)
from workers.policy.network import Policy, PolicyWeights
from workers.policy.observations import ObservationReader
from workers.rollout import BatchEvaluator
from workers.tasks import make_task
from workers.tasks.base import SimStates

EPISODE_FIELDS = ("model_params", "goal")
"""Fields of a SimStates tree fixed within an episode; all others are per-step arrays."""


def states_chunk(states: SimStates, start: int, stop: int) -> dict[str, Any]:
    """The SimStates tree of steps ``start:stop`` of an episode (what a relabeling call takes)."""
    return {k: (v if k in EPISODE_FIELDS else v[start:stop]) for k, v in states.to_tree().items()}


class RelabelWorker:
    """Expert episodes, policy episodes and DAgger relabeling of one task.

    Args:
        task_name: registry name of the task.
        task_options: the task's options.
        threads: native rollout threads (the CPUs the worker holds).
    """

    def __init__(self, task_name: str, task_options: dict[str, Any] | None = None, threads: int = 1):
        self.task = make_task(task_name, task_options)
        self.env = self.task.make_env()
        self.env.reset(seed=0)
        self.scratch = self.task.make_env()
        self.scratch.reset(seed=0)
        self.model = self.task.build_planning_model(self.env)
        self.evaluator = BatchEvaluator(self.task, self.model, max(1, int(threads)))
        self.reader = ObservationReader(self.task, self.scratch)

    def expert(self, settings: ExpertSettings, seed: int) -> ICemPi:
        """A fresh iCEM_pi expert on this worker's simulation."""
        return ICemPi(self.task, self.model, self.evaluator, self.reader, self.scratch, settings, seed)

    @staticmethod
    def _policy(weights: PolicyWeights | None) -> Policy | None:
        return None if weights is None else Policy(weights)

    def expert_episode(
        self, seed: int, steps: int, weights: PolicyWeights | None, settings: ExpertSettings
    ) -> ExpertEpisode:
        """An expert episode from ``reset(seed)``; the policy guides it as the settings say."""
        policy = self._policy(weights) if settings.uses_policy else None
        return run_expert_episode(self.task, self.env, self.expert(settings, seed), policy, seed, steps)

    def policy_episode(self, seed: int, steps: int, weights: PolicyWeights) -> PolicyEpisode:
        """A policy episode from ``reset(seed)``, with the simulator state before every step."""
        return run_policy_episode(self.task, self.env, Policy(weights), seed, steps)

    def relabel(
        self,
        states: dict[str, Any],
        observations: np.ndarray,
        weights: PolicyWeights | None,
        seed: int,
        settings: ExpertSettings,
    ) -> RelabeledChunk:
        """The expert's actions at consecutive recorded states (a SimStates tree) and their observations."""
        policy = self._policy(weights) if settings.uses_policy else None
        expert = self.expert(settings, seed)
        return relabel_states(expert, SimStates.from_tree(states), np.asarray(observations), policy, seed)

    def pid(self) -> int:
        """Process id (fault-injection tests)."""
        return os.getpid()

    def close(self) -> None:
        self.evaluator.close()
        self.env.close()
        self.scratch.close()
