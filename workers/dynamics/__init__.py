"""Learned probabilistic-ensemble dynamics and uncertainty-aware planning costs (thesis chapter 5, appendix D).

* :mod:`~workers.dynamics.ensemble`: the probabilistic ensemble, its training and checkpoints (eq. 19, App. D.2.1).
* :mod:`~workers.dynamics.propagation`: PETSUS, TS1 particles plus mean propagation (eq. 20-24).
* :mod:`~workers.dynamics.costs`: RAZER's cost terms (eq. 25-27, 34-35).
* :mod:`~workers.dynamics.evaluator`: the planner-facing cost function.
* :mod:`~workers.dynamics.benchmark`: evaluator throughput against dense matmuls.

Pure torch / numpy: nothing here imports Ray or MLflow.
"""

from workers.dynamics.benchmark import (
    ThroughputReport,
    dense_matmul_flops_per_second,
    ensemble_evaluator_particle_steps_per_second,
    measure_ensemble_throughput,
)
from workers.dynamics.costs import CostTerms, RazerSettings, SafetyBox, TaskCost, sequence_costs
from workers.dynamics.ensemble import (
    ENSEMBLE_PRESETS,
    DynamicsEnsemble,
    EnsembleConfig,
    TrainStats,
    Transitions,
    gaussian_nll,
)
from workers.dynamics.evaluator import DEFAULT_PARTICLES, EnsembleEvaluator
from workers.dynamics.propagation import MeanPropagation, Propagation, petsus_propagate

__all__ = [
    "DEFAULT_PARTICLES",
    "ENSEMBLE_PRESETS",
    "CostTerms",
    "DynamicsEnsemble",
    "EnsembleConfig",
    "EnsembleEvaluator",
    "MeanPropagation",
    "Propagation",
    "RazerSettings",
    "SafetyBox",
    "TaskCost",
    "ThroughputReport",
    "TrainStats",
    "Transitions",
    "dense_matmul_flops_per_second",
    "ensemble_evaluator_particle_steps_per_second",
    "gaussian_nll",
    "measure_ensemble_throughput",
    "petsus_propagate",
    "sequence_costs",
]
