"""The EnsembleTrainer: the ``mbrl`` method's stateful role that fits the ensemble between episodes.

One trainer per trial holds the :class:`~workers.dynamics.ensemble.DynamicsEnsemble`
and its Adam state. Each MBRL iteration the program hands it the whole dataset
by reference (one ``share`` per round) and gets back versioned weights
(:class:`Weights`, numpy arrays: they travel through the object store once
and every planning worker rebuilds the model from them) and the training
figures. Its state (weights, normaliser, Adam moments, version) is pulled into
the trial's checkpoint after every round and pushed back on restore, so a
trainer lost mid-training costs only the round in flight.

Plain Python: the orchestrator wraps it in a Ray actor holding ``cpus`` CPUs,
tests build it in-process.
"""

from __future__ import annotations

import os
from typing import Any, NamedTuple

import numpy as np

from workers.dynamics.ensemble import DynamicsEnsemble, Transitions
from workers.dynamics.settings import EnsembleConfig


class Weights(NamedTuple):
    """A version of the ensemble's weights, as planning workers receive it (no optimiser state)."""

    version: int
    """Weights version: +1 per training call (0: the untrained initial weights)."""
    arrays: dict[str, np.ndarray]
    """Parameters and input normaliser (:meth:`DynamicsEnsemble.export_weights`)."""
    meta: dict[str, Any]
    """Shapes, config and seed needed to rebuild the model."""

    def model(self) -> DynamicsEnsemble:
        """The ensemble these weights describe."""
        return DynamicsEnsemble.from_state(self.arrays, self.meta)

    @classmethod
    def of(cls, model: DynamicsEnsemble) -> Weights:
        arrays, meta = model.export_weights()
        return cls(model.weights_version, arrays, meta)


class TrainReport(NamedTuple):
    """What one training call returns."""

    weights: Weights
    """The weights after training."""
    metrics: dict[str, float]
    """train_nll, train_mse, held_out_nll, held_out_mse (when there was a held-out set), logvar_at_min,
    logvar_at_max, logvar_at_bound (fractions of predicted log-variances within 0.1 of a bound, training
    data), train_seconds, gradient_steps, weights_version."""


class EnsembleTrainer:
    """Trains a probabilistic ensemble on the datasets it is given; stateful across calls.

    Args:
        obs_dim: state dimensions.
        action_dim: action dimensions.
        config: the ensemble's architecture and training settings (an EnsembleConfig as a dict).
        seed: seeds the initial weights.
        cpus: CPUs this worker holds; torch uses as many threads.
    """

    def __init__(self, obs_dim: int, action_dim: int, config: dict[str, Any], seed: int = 0, cpus: float = 1):
        import torch

        torch.set_num_threads(max(1, int(cpus)))
        self.model = DynamicsEnsemble(obs_dim, action_dim, EnsembleConfig(**config), seed=seed)

    def train(
        self, dataset: Transitions, held_out_from: int | None, seed: int, epochs: int | None = None
    ) -> TrainReport:
        """Evaluate the newest data before training on it, then train on all of ``dataset``.

        Args:
            dataset: every transition so far (passed by reference).
            held_out_from: index of the first transition of the newest episode: rows from here on are
                evaluated (held-out NLL and MSE) with the current weights *before* training on them;
                None, or untrained weights: no held-out figures.
            seed: seeds the minibatch order of this call.
            epochs: epochs of this call; None: the config's.
        """
        dataset = Transitions(*(np.asarray(part) for part in dataset))
        metrics: dict[str, float] = {}
        if held_out_from is not None and held_out_from < len(dataset) and self.model.weights_version > 0:
            held_out = Transitions(*(part[held_out_from:] for part in dataset))
            nll, mse, _, _ = self.model.evaluate(held_out)
            metrics |= {"held_out_nll": nll, "held_out_mse": mse}
        stats = self.model.train(dataset, epochs=epochs, seed=seed)
        metrics |= {
            "train_nll": stats.train_nll,
            "train_mse": stats.train_mse,
            "logvar_at_min": stats.at_min_logvar,
            "logvar_at_max": stats.at_max_logvar,
            "logvar_at_bound": stats.at_min_logvar + stats.at_max_logvar,
            "train_seconds": stats.seconds,
            "gradient_steps": float(stats.gradient_steps),
            "weights_version": float(stats.weights_version),
        }
        return TrainReport(Weights.of(self.model), metrics)

    def load_weights(self, weights: Weights) -> Weights:
        """Start from given weights (a model trained elsewhere), with a fresh optimiser; returns them."""
        self.model.import_state(weights.arrays, weights.meta)
        return Weights.of(self.model)

    def weights(self) -> Weights:
        """The current weights."""
        return Weights.of(self.model)

    # ------------------------------------------------------------ state
    def state_dict(self) -> dict[str, Any]:
        """Weights, normaliser, Adam state and version as a checkpoint tree (no pickle)."""
        arrays, meta = self.model.export_state()
        return {"arrays": arrays, "meta": meta}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Continue from :meth:`state_dict` (of a trainer of the same shape and config)."""
        self.model.import_state({k: np.asarray(v) for k, v in state["arrays"].items()}, state["meta"])

    def pid(self) -> int:
        """Process id (fault-injection tests)."""
        return os.getpid()
