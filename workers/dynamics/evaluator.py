"""The planner-facing cost evaluator: numpy action sequences in, RAZER costs out (Alg. 5 lines 6-8).

The iCEM planner (workers/planning/icem.py) minimises a function of (N, h, d)
action sequences in [-1, 1]. :class:`EnsembleEvaluator` computes that cost
for a start observation with one PETSUS propagation and one batched task-cost
call per invocation: torch never runs per trajectory.

The ensemble must have been trained on actions in the planner's normalised
[-1, 1] space (the tasks' ``env_action`` maps them to the environment).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch

from workers.dynamics.costs import CostTerms, RazerSettings, TaskCost, sequence_costs, terms_as_numpy
from workers.dynamics.ensemble import DynamicsEnsemble
from workers.dynamics.propagation import Propagation, petsus_propagate

DEFAULT_PARTICLES = 5
"""Particles per sequence. The thesis does not give P; PETS used 20. One per member of a 5-ensemble keeps
the 6 x 400 BridgeMaze model affordable on a two-core machine; raise it when it fits."""


class EnsembleEvaluator:
    """RAZER / PETS costs of action sequences under a learned ensemble.

    Args:
        model: the trained ensemble.
        task_cost: per-transition planning cost c(s, a, s') on torch batches (a task's ``planning_cost``).
        settings: weights and switches (default: PETS).
        particles: P, TS1 particles per sequence.
        seed: seeds the torch generator of particle noise and TS1 assignment; the same seed and the
            same calls give the same costs.
        project: moves predicted states onto the task's state set (a task's ``project_states``); None: no move.
    """

    def __init__(
        self,
        model: DynamicsEnsemble,
        task_cost: TaskCost,
        settings: RazerSettings | None = None,
        particles: int = DEFAULT_PARTICLES,
        seed: int = 0,
        project: Callable[[torch.Tensor], torch.Tensor] | None = None,
    ):
        self.model = model
        self.project = project
        self.task_cost = task_cost
        self.settings = settings or RazerSettings.pets()
        if particles < 1:
            raise ValueError(f"particles must be at least 1, got {particles}")
        self.particles = particles
        used_dims = list(self.settings.uncertainty_dims or ()) + [
            d for box in self.settings.safety_boxes for d in box.dims
        ]
        if used_dims and max(used_dims) >= model.obs_dim:
            raise ValueError(f"settings refer to observation dimension {max(used_dims)}; the model has {model.obs_dim}")
        self.reseed(seed)

    def reseed(self, seed: int) -> None:
        """Restart the random stream (e.g. per episode, for reproducible episodes)."""
        self.generator = torch.Generator().manual_seed(seed)

    def propagate(self, observation: np.ndarray, actions: np.ndarray) -> Propagation:
        """The PETSUS propagation of the sequences (for inspection and tests).

        Mean states are propagated only where a cost reads them (``RazerSettings.propagated_means``); without
        them u_E is not reported.
        """
        mean_propagation = self.settings.propagated_means()
        with torch.no_grad():
            return petsus_propagate(
                self.model,
                torch.as_tensor(observation, dtype=torch.float32),
                torch.as_tensor(actions, dtype=torch.float32),
                self.particles,
                mean_propagation,
                self.generator,
                self.settings.epistemic_terms,
                self.project,
                self.settings.aleatoric_states,
            )

    def terms(self, observation: np.ndarray, actions: np.ndarray) -> CostTerms:
        """All cost terms as torch tensors."""
        propagation = self.propagate(observation, actions)
        with torch.no_grad():
            return sequence_costs(propagation, torch.as_tensor(actions), self.task_cost, self.settings)

    def costs(self, observation: np.ndarray, actions: np.ndarray) -> tuple[np.ndarray, dict[str, np.ndarray]]:
        """(total (N,), components) for (N, h, d) action sequences from ``observation``.

        Components, each (N,): ``c`` task cost (eq. 25), ``c_A`` aleatoric penalty (eq. 26),
        ``c_E`` epistemic bonus (eq. 27, <= 0), ``c_S`` safety penalty (eq. 35), ``u_A`` and
        ``u_E`` the unweighted uncertainty sums (``u_E`` only with mean propagation and w_E > 0), and
        ``violation_steps``. ``total`` = c + c_A + c_E + c_S.
        """
        return terms_as_numpy(self.terms(observation, actions))

    def cost_function(self, observation: np.ndarray) -> Callable[[np.ndarray], np.ndarray]:
        """The planner's CostFunction for one state: action sequences (N, h, d) -> total costs (N,)."""
        return lambda actions: self.costs(observation, actions)[0]
