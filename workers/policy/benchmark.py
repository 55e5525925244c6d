"""Measurements for ``icemlab bench``: DAgger relabeling throughput and policy training speed.

* :func:`relabel_rates`: relabeled states per second through one role group of RelabelWorkers and
  through another (e.g. one worker, then two), on the same chunks, back to back. The groups are any
  :class:`~workers.methods.base.RoleGroup`: in-process workers for a quick look, Ray actors when the
  service runs it (the figure that matters: workers in separate processes on separate cores).
* :func:`training_rates`: gradient steps per second of the policy trainer with 1 and 2 torch threads.

Only measures; asserts nothing. Timings on a shared machine vary by tens of percent.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from typing import Any, NamedTuple

import numpy as np

from workers.methods.base import RoleGroup
from workers.planning import PlannerConfig
from workers.policy.expert import ExpertSettings
from workers.policy.network import PolicyWeights
from workers.policy.training import PolicySettings, PolicyTrainer


class RelabelWorkload(NamedTuple):
    """Chunks of recorded states to relabel, the policy that guides the expert, and its settings."""

    chunks: list[tuple[dict[str, Any], np.ndarray]]
    """(SimStates tree, observations) per chunk."""
    weights: PolicyWeights
    settings: ExpertSettings

    @property
    def states(self) -> int:
        return sum(len(observations) for _, observations in self.chunks)


def relabel_workload(
    task_name: str, states: int = 40, chunk: int = 10, budget: int = 45, horizon: int = 30, seed: int = 0
) -> RelabelWorkload:
    """A policy episode of a randomly initialised policy, cut into chunks (built in this process)."""
    from workers.policy.worker import RelabelWorker, states_chunk

    worker = RelabelWorker(task_name)
    try:
        observation, _ = worker.env.reset(seed=seed)
        obs_dim = len(worker.task.observe(observation))
        weights = PolicyTrainer(seed, task=task_name, obs_dim=obs_dim, action_dim=worker.task.action_dim).weights()
        trajectory = worker.policy_episode(seed, states, weights).trajectory
    finally:
        worker.close()
    sim = trajectory.sim_states
    chunks = []
    for start in range(0, len(trajectory), chunk):
        stop = min(start + chunk, len(trajectory))
        tree = states_chunk(sim, start, stop)
        chunks.append((tree, trajectory.observations[start:stop]))
    from workers.tasks import make_task

    planner = PlannerConfig(budget=budget, horizon=horizon).resolved(make_task(task_name).colored_noise_beta)
    return RelabelWorkload(chunks, weights, ExpertSettings(planner=planner))


def relabel_states_per_second(group: RoleGroup, workload: RelabelWorkload) -> float:
    """Relabeled states per second through ``group`` (one ``share`` of the weights, chunks spread by ``map``)."""
    shared = group.share(workload.weights)
    calls = [(tree, obs, shared, index, workload.settings) for index, (tree, obs) in enumerate(workload.chunks)]
    started = time.perf_counter()
    group.map("relabel", calls)
    return workload.states / (time.perf_counter() - started)


def relabel_rates(groups: Sequence[RoleGroup], workload: RelabelWorkload) -> dict[str, Any]:
    """States per second through each group, back to back, and each rate relative to the first group's."""
    for group in groups:  # warm-up: first calls build caches and thread pools
        shared = group.share(workload.weights)
        tree, obs = workload.chunks[0]
        first = {k: (v if k in ("model_params", "goal") else v[:1]) for k, v in tree.items()}
        group.map("relabel", [(first, obs[:1], shared, 0, workload.settings)] * group.size)
    rates = [relabel_states_per_second(group, workload) for group in groups]
    return {
        "workers": [group.size for group in groups],
        "states_per_second": rates,
        "ratio_to_first": [rate / rates[0] for rate in rates],
        "states": workload.states,
        "chunks": len(workload.chunks),
    }


def training_rates(
    obs_dim: int, action_dim: int, threads: Sequence[int] = (1, 2), steps: int = 200, samples: int = 50_000
) -> dict[str, Any]:
    """Gradient steps per second of the policy trainer (batch 1024, 3 x 128) at each torch thread count."""
    import torch

    rng = np.random.default_rng(0)
    dataset = {
        "observations": rng.normal(size=(samples, obs_dim)),
        "actions": rng.uniform(-1, 1, size=(samples, action_dim)),
    }
    previous = torch.get_num_threads()
    rates = []
    try:
        for count in threads:
            trainer = PolicyTrainer(0, PolicySettings(), cpus=count, obs_dim=obs_dim, action_dim=action_dim)
            trainer.train(dataset, steps=5)  # warm-up
            report = trainer.train(dataset, steps=steps)
            rates.append(steps / report.seconds)
    finally:
        torch.set_num_threads(previous)
    return {"threads": list(threads), "steps_per_second": rates, "ratio_to_first": [r / rates[0] for r in rates]}
