"""Learned probabilistic-ensemble dynamics and uncertainty-aware planning costs (thesis chapter 5, appendix D).

* :mod:`~workers.dynamics.settings`: the pydantic settings (no torch): EnsembleConfig, RazerSettings, SafetyBox.
* :mod:`~workers.dynamics.ensemble`: the probabilistic ensemble, its training and checkpoints (eq. 19, App. D.2.1).
* :mod:`~workers.dynamics.propagation`: PETSUS, TS1 particles plus mean propagation (eq. 20-24).
* :mod:`~workers.dynamics.costs`: RAZER's cost terms (eq. 25-27, 34-35).
* :mod:`~workers.dynamics.evaluator`: the planner-facing cost function.
* :mod:`~workers.dynamics.ground_truth`: the same costs over an ensemble of noisy ground-truth simulators.
* :mod:`~workers.dynamics.trainer`: the EnsembleTrainer worker (the ``mbrl`` method's stateful role).
* :mod:`~workers.dynamics.episodes`: MPC episodes on a learned model, and the planning worker.
* :mod:`~workers.dynamics.benchmark`: evaluator throughput against dense matmuls.

Pure torch / numpy: nothing here imports Ray or MLflow. Names are imported
lazily, so that importing the torch-free settings does not import torch.
"""

from __future__ import annotations

import importlib
from typing import Any

_EXPORTS = {
    "ThroughputReport": "benchmark",
    "dense_matmul_flops_per_second": "benchmark",
    "ensemble_evaluator_particle_steps_per_second": "benchmark",
    "measure_ensemble_throughput": "benchmark",
    "CostTerms": "costs",
    "TaskCost": "costs",
    "sequence_costs": "costs",
    "DynamicsEnsemble": "ensemble",
    "TrainStats": "ensemble",
    "Transitions": "ensemble",
    "gaussian_nll": "ensemble",
    "DEFAULT_PARTICLES": "evaluator",
    "EnsembleEvaluator": "evaluator",
    "GroundTruthEnsembleEvaluator": "ground_truth",
    "StateDraws": "ground_truth",
    "Propagation": "propagation",
    "petsus_propagate": "propagation",
    "ENSEMBLE_PRESETS": "settings",
    "PRESET_SHAPES": "settings",
    "EnsembleConfig": "settings",
    "MeanPropagation": "settings",
    "RazerSettings": "settings",
    "SafetyBox": "settings",
    "EnsembleTrainer": "trainer",
    "Weights": "trainer",
    "PlanningWorker": "episodes",
}


def __getattr__(name: str) -> Any:
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module 'workers.dynamics' has no attribute {name!r}")
    value = getattr(importlib.import_module(f"workers.dynamics.{module}"), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted([*globals(), *_EXPORTS])


__all__ = sorted(_EXPORTS)
