"""The improved Cross-Entropy Method for model-predictive control (thesis chapter 3).

:class:`CEMPlanner` implements the "Proposed iCEM algorithm" (section 3.2,
Alg. 4 in the thesis numbering of chapter 3) with every improvement behind its
own switch of :class:`~workers.planning.config.PlannerConfig`; with the
switches off it is CEM_MPC, CEM_PETS or plain CEM (Alg. 1). The planner only
sees a cost function over batches of action sequences, so the same code plans
with ground-truth simulation, learned models or guided costs.

Actions are normalised to [-1, 1] in every dimension; tasks map them to their
action spaces, which makes sigma_init a fraction of the half action range as in
the authors' implementation.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import numpy as np

from workers.planning.config import PlannerConfig
from workers.planning.noise import colored_noise, truncated_normal

CostFunction = Callable[[np.ndarray], np.ndarray]
"""Maps action sequences (N, h, d) in [-1, 1] to their costs (N,); lower is better."""

LOW, HIGH = -1.0, 1.0


class PlanResult(NamedTuple):
    """The outcome of planning one environment step."""

    action: np.ndarray
    """(d,) action to execute, in [-1, 1]."""
    best_cost: float
    """Lowest cost among the sequences evaluated at this step."""
    trajectories: int
    """Action sequences evaluated at this step (the budget spent)."""
    plan: np.ndarray
    """(h, d) the sequence whose first action is executed (best sequence or mean)."""


class CEMPlanner:
    """iCEM and the CEM baselines as one MPC planner with switchable components.

    Args:
        config: a resolved planner config (:meth:`PlannerConfig.resolved`).
        action_dim: number of action dimensions d.
        seed: seed of the planner's random generator; the same seed and the
            same costs give the same actions.
    """

    def __init__(self, config: PlannerConfig, action_dim: int, seed: int = 0):
        if config.iterations is None or config.population is None or config.noise_beta is None:
            raise ValueError("CEMPlanner needs a resolved config (PlannerConfig.resolved)")
        self.config = config
        self.action_dim = action_dim
        self.shape = (config.horizon, action_dim)
        self.population_sizes = config.population_sizes()
        self.reused = config.reused_elites()
        self.reset(seed)

    def reset(self, seed: int | None = None) -> None:
        """Forget the shifted mean and elites (start of an episode)."""
        if seed is not None:
            self.rng = np.random.default_rng(seed)
        self.mean = np.zeros(self.shape)
        self.previous_elites: np.ndarray | None = None

    # ---------------------------------------------------------- sampling
    def _sample(self, mean: np.ndarray, std: np.ndarray, count: int) -> np.ndarray:
        config = self.config
        if config.bounds == "clip":
            # Colored noise C^beta(d, h): correlations run along time (section 3.2.1).
            noise = colored_noise(config.noise_beta, (count, self.action_dim, config.horizon), self.rng)
            # The thesis pseudo-code writes sigma^2 but scales by the standard deviation.
            return np.clip(mean + noise.transpose(0, 2, 1) * std, LOW, HIGH)
        if config.bounds == "truncate":
            return truncated_normal(mean, std, LOW, HIGH, count, self.rng)
        # truncate_2sigma (CEM_PETS): sigma is capped at half the distance to the bounds.
        return truncated_normal(mean, std, mean - 2 * std, mean + 2 * std, count, self.rng)

    def _cap_std(self, mean: np.ndarray, std: np.ndarray) -> np.ndarray:
        if self.config.bounds != "truncate_2sigma":
            return std
        return np.minimum(std, np.minimum(mean - LOW, HIGH - mean) / 2.0)

    def _shifted_elites(self, mean: np.ndarray, std: np.ndarray) -> np.ndarray:
        """Last step's best elites moved one step in time, with a fresh random last action."""
        kept = self.previous_elites[: self.reused]
        fresh = self._sample(mean, std, len(kept))[:, -1:]
        return np.concatenate([kept[:, 1:], fresh], axis=1)

    # ---------------------------------------------------------- planning
    def plan(self, cost_function: CostFunction) -> PlanResult:
        """Optimise the action sequence for the current state; return the action to execute."""
        config = self.config
        mean = self.mean
        std = self._cap_std(mean, np.full(self.shape, config.sigma_init))  # sigma reset every step
        elites = elite_costs = None
        best_cost, best_sequence = np.inf, None
        evaluated = 0
        last = config.iterations - 1

        for i, count in enumerate(self.population_sizes):
            samples = self._sample(mean, std, count)
            if i == last and config.add_mean:
                # The mean takes the place of one sample, which keeps the budget of
                # Table 4 (as in the authors' implementation); B.4.3: last iteration only.
                samples[0] = mean
            if i == 0 and config.shift_elites and self.previous_elites is not None and self.reused:
                samples = np.concatenate([samples, self._shifted_elites(mean, std)])
            costs = np.asarray(cost_function(samples), dtype=np.float64)
            if costs.shape != (len(samples),):
                raise ValueError(f"cost function returned shape {costs.shape}, expected ({len(samples)},)")
            costs = np.where(np.isfinite(costs), costs, np.inf)
            evaluated += len(samples)

            if i > 0 and config.keep_elites and self.reused:
                # Deterministic ground truth: kept elites keep their costs.
                samples = np.concatenate([samples, elites[: self.reused]])
                costs = np.concatenate([costs, elite_costs[: self.reused]])

            order = np.argsort(costs, kind="stable")[: config.elites]
            elites, elite_costs = samples[order], costs[order]
            if elite_costs[0] < best_cost:
                best_cost, best_sequence = float(elite_costs[0]), elites[0].copy()

            alpha = config.momentum
            mean = alpha * mean + (1 - alpha) * elites.mean(axis=0)
            std = self._cap_std(mean, alpha * std + (1 - alpha) * elites.std(axis=0))

        plan = best_sequence if config.best_action else mean
        action = plan[0].copy()

        # Shift initialisation of the next step's mean (eq. 32-33).
        if config.shift_mean:
            tail = mean[-1:] if config.shift_last == "repeat" else np.zeros((1, self.action_dim))
            self.mean = np.concatenate([mean[1:], tail])
        else:
            self.mean = np.zeros(self.shape)
        self.previous_elites = elites
        return PlanResult(action, best_cost, evaluated, plan.copy())
