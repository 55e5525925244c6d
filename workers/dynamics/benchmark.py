"""Throughput of the ensemble evaluator against plain dense matmuls of the same layer sizes.

Acceptance criterion of the issue: the evaluator's achieved FLOP rate (linear
layers only) is at least half of what the same machine reaches with plain
dense matmuls of the same shapes. :func:`measure_ensemble_throughput` measures
both in one call, alternating, so that both see the same machine load. It
only measures; no figure is asserted anywhere.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from typing import NamedTuple

import numpy as np
import torch

from workers.dynamics.costs import RazerSettings
from workers.dynamics.ensemble import DynamicsEnsemble, EnsembleConfig
from workers.dynamics.evaluator import EnsembleEvaluator
from workers.dynamics.propagation import MeanPropagation


class ThroughputReport(NamedTuple):
    """Both measurements of :func:`measure_ensemble_throughput`."""

    dense_flops_per_second: float
    """Plain (batch, in) @ (in, out) chain over the layer sizes, best of the repeats."""
    particle_steps_per_second: float
    """Particle model steps (N P h per call) of the evaluator per second, best of the repeats."""
    ensemble_flops_per_second: float
    """Linear-layer FLOPs the evaluator performed per second (particle and mean-state rows)."""
    ratio: float
    """ensemble_flops_per_second / dense_flops_per_second (acceptance: >= 0.5)."""
    rows_per_model_step: int
    """Rows one model step evaluates over all members (the dense benchmark's batch)."""
    threads: int
    """torch.get_num_threads() during the measurement."""


def _best_seconds(run: Callable[[], object], repeats: int) -> float:
    run()  # warm-up: allocations, thread pools
    best = np.inf
    for _ in range(repeats):
        started = time.perf_counter()
        run()
        best = min(best, time.perf_counter() - started)
    return float(best)


def mlp_flops(layer_sizes: Sequence[int], rows: int) -> float:
    """Multiply-add FLOPs (2 per MAC) of one pass of ``rows`` inputs through linear layers of these sizes."""
    return 2.0 * rows * sum(i * o for i, o in zip(layer_sizes[:-1], layer_sizes[1:]))


def dense_matmul_flops_per_second(layer_sizes: Sequence[int], batch: int, repeats: int = 5) -> float:
    """FLOP/s of a chain of plain float32 matmuls (batch, in) @ (in, out) over ``layer_sizes``."""
    generator = torch.Generator().manual_seed(0)
    weights = [torch.randn(i, o, generator=generator) / i**0.5 for i, o in zip(layer_sizes[:-1], layer_sizes[1:])]
    x = torch.randn(batch, layer_sizes[0], generator=generator)

    def run() -> torch.Tensor:
        h = x
        for w in weights:
            h = h @ w
        return h

    with torch.no_grad():
        seconds = _best_seconds(run, repeats)
    return mlp_flops(layer_sizes, batch) / seconds


def ensemble_evaluator_particle_steps_per_second(
    evaluator: EnsembleEvaluator, observation: np.ndarray, actions: np.ndarray, repeats: int = 3
) -> float:
    """Particle model steps per second of ``evaluator.costs`` on (N, h, d) ``actions``."""
    n, horizon, _ = actions.shape
    seconds = _best_seconds(lambda: evaluator.costs(observation, actions), repeats)
    return n * evaluator.particles * horizon / seconds


def measure_ensemble_throughput(
    config: EnsembleConfig,
    obs_dim: int,
    action_dim: int,
    sequences: int = 128,
    particles: int = 5,
    horizon: int = 30,
    mean_propagation: MeanPropagation = "per_member",
    repeats: int = 3,
    rounds: int = 3,
) -> ThroughputReport:
    """Measure dense matmuls and the evaluator on the same layer sizes (random weights), alternating.

    ``rounds`` alternations of (dense, evaluator), each the best of ``repeats``; the best of each over
    the rounds is kept. Alternating spreads both over the same stretch of time, so a change of the
    machine's clock or load during the measurement moves both sides rather than one.
    """
    model = DynamicsEnsemble(obs_dim, action_dim, config)
    # Mean states are propagated only for an epistemic bonus: give it one wherever the mean rows are counted.
    bonus = 0.0 if mean_propagation == "none" else 0.05
    settings = RazerSettings(mean_propagation=mean_propagation, epistemic_weight=bonus)
    evaluator = EnsembleEvaluator(model, lambda s, a, s2: s2.sum(dim=-1), settings, particles)
    k = config.ensemble_size
    per = -(-particles // k)
    mean_rows = {"none": 0, "shared": 1, "per_member": 1}[mean_propagation] * sequences
    rows = k * (sequences * per + mean_rows)
    sizes = model.net.layer_sizes
    rng = np.random.default_rng(0)
    observation = rng.normal(size=obs_dim)
    actions = rng.uniform(-1, 1, size=(sequences, horizon, action_dim))

    dense, steps = 0.0, 0.0
    for _ in range(rounds):
        dense = max(dense, dense_matmul_flops_per_second(sizes, rows, repeats=repeats))
        steps = max(steps, ensemble_evaluator_particle_steps_per_second(evaluator, observation, actions, repeats))
    ensemble_flops = steps / (sequences * particles) * mlp_flops(sizes, rows)
    return ThroughputReport(
        dense_flops_per_second=dense,
        particle_steps_per_second=steps,
        ensemble_flops_per_second=ensemble_flops,
        ratio=ensemble_flops / dense,
        rows_per_model_step=rows,
        threads=torch.get_num_threads(),
    )
