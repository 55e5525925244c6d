"""The improved Cross-Entropy Method for model-predictive control (thesis chapter 3).

:class:`CEMPlanner` implements the "Proposed iCEM algorithm" (section 3.2,
Alg. 4 in the thesis numbering of chapter 3) with every improvement behind its
own switch of :class:`~workers.planning.config.PlannerConfig`; with the
switches off it is CEM_MPC, CEM_PETS or plain CEM (Alg. 1). The planner only
sees a cost function over batches of action sequences, so the same code plans
with ground-truth simulation, learned models or guided costs:

* a cost function returns either costs (N,) or a :class:`CostBatch`: costs
  per particle (N, P) with the name of their aggregate (stochastic models,
  chapter 5), and named further cost terms (chapter 4's guidance term) that an
  :data:`Objective` weighs into the cost that ranks the samples;
* the planner's memory between environment steps (the shifted mean and the
  last elites) is an explicit :class:`PlannerMemory`, so a relabeling expert
  can plan from any state with any warm start (chapter 4);
* callers can add candidate sequences of their own (``proposals``, e.g. a
  policy's h-step plan, App. C.2) to the last CEM-iteration.

Actions are normalised to [-1, 1] in every dimension; tasks map them to their
action spaces, which makes sigma_init a fraction of the half action range as in
the authors' implementation.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any, Literal, NamedTuple

import numpy as np

from workers.checkpoint import restore_rng, rng_state
from workers.planning.config import PlannerConfig
from workers.planning.noise import colored_noise, truncated_normal

LOW, HIGH = -1.0, 1.0

Aggregate = Literal["mean", "max", "min"]
"""How the costs of a sequence's particles reduce to one: their mean (PETS, chapter 5), worst or best case."""

_AGGREGATES: dict[str, Callable[[np.ndarray], np.ndarray]] = {
    "mean": lambda costs: costs.mean(axis=1),
    "max": lambda costs: costs.max(axis=1),
    "min": lambda costs: costs.min(axis=1),
}


class CostBatch(NamedTuple):
    """What an evaluator says about N action sequences."""

    costs: np.ndarray
    """(N,) summed cost of each sequence, or (N, P) per particle of a stochastic model."""
    aggregate: Aggregate = "mean"
    """How per-particle costs reduce to one cost per sequence."""
    components: Mapping[str, np.ndarray] = {}
    """(N,) named further terms: weighed in by an objective (APEX guidance) or logged (RAZER's c_A, c_E, c_S)."""

    def main(self) -> np.ndarray:
        """(N,) the cost per sequence, particles reduced by the aggregate."""
        if self.costs.ndim == 1:
            return self.costs
        return _AGGREGATES[self.aggregate](self.costs)

    def take(self, index: np.ndarray) -> CostBatch:
        """The rows ``index`` (kept elites travel with their costs and terms)."""
        return CostBatch(self.costs[index], self.aggregate, {k: v[index] for k, v in self.components.items()})

    @staticmethod
    def concatenate(first: CostBatch, second: CostBatch) -> CostBatch:
        if set(first.components) != set(second.components):
            raise ValueError("cost batches with different components cannot be joined")
        return CostBatch(
            np.concatenate([first.costs, second.costs]),
            first.aggregate,
            {k: np.concatenate([first.components[k], second.components[k]]) for k in first.components},
        )


CostFunction = Callable[[np.ndarray], "np.ndarray | CostBatch"]
"""Maps action sequences (N, h, d) in [-1, 1] to their costs (N,) or a CostBatch; lower is better."""

Objective = Callable[[CostBatch, int], np.ndarray]
"""Ranks samples: (cost batch of every candidate of a CEM-iteration, iteration index) -> (N,) costs."""


def main_cost(batch: CostBatch, iteration: int) -> np.ndarray:
    """The default objective: the evaluator's cost, particles reduced by its aggregate."""
    return batch.main()


class PlannerMemory(NamedTuple):
    """What the planner carries from one environment step to the next."""

    mean: np.ndarray
    """(h, d) the initial mean of the next plan (shift-initialised, eq. 32-33)."""
    elites: np.ndarray | None
    """(K, h, d) the final elite-set of the last plan, for shift-elites; None at the start of an episode."""


class PlanResult(NamedTuple):
    """The outcome of planning one environment step."""

    action: np.ndarray
    """(d,) action to execute, in [-1, 1]."""
    best_cost: float
    """Lowest objective cost among the sequences evaluated at this step."""
    trajectories: int
    """Action sequences evaluated at this step (the budget spent)."""
    plan: np.ndarray
    """(h, d) the sequence whose first action is executed (best sequence or mean)."""
    mean: np.ndarray
    """(h, d) the final mean of the sampling distribution (before shifting)."""
    components: dict[str, float]
    """The evaluator's further cost terms of the best sequence (empty for plain costs)."""


class CEMPlanner:
    """iCEM and the CEM baselines as one MPC planner with switchable components.

    Args:
        config: a resolved planner config (:meth:`PlannerConfig.resolved`).
        action_dim: number of action dimensions d.
        seed: seed of the planner's random generator; the same seed and the
            same costs give the same actions.
        objective: ranks the candidates of a CEM-iteration from their cost
            batch (default: the evaluator's cost).
    """

    def __init__(self, config: PlannerConfig, action_dim: int, seed: int = 0, objective: Objective = main_cost):
        if config.iterations is None or config.population is None or config.noise_beta is None:
            raise ValueError("CEMPlanner needs a resolved config (PlannerConfig.resolved)")
        self.config = config
        self.action_dim = action_dim
        self.shape = (config.horizon, action_dim)
        self.population_sizes = config.population_sizes()
        self.reused = config.reused_elites()
        self.objective = objective
        self.reset(seed)

    def reset(self, seed: int | None = None) -> None:
        """Forget the shifted mean and elites (start of an episode)."""
        if seed is not None:
            self.rng = np.random.default_rng(seed)
        self.memory = self.initial_memory()

    def initial_memory(self, mean: np.ndarray | None = None) -> PlannerMemory:
        """Memory of a fresh start: a zero mean (or ``mean``, e.g. a policy's warm start) and no elites."""
        start = np.zeros(self.shape) if mean is None else np.asarray(mean, dtype=np.float64).reshape(self.shape)
        return PlannerMemory(start, None)

    @property
    def mean(self) -> np.ndarray:
        """The initial mean of the next plan."""
        return self.memory.mean

    # ---------------------------------------------------------- state
    def state_dict(self) -> dict[str, Any]:
        """Memory and random-generator state, as checkpoint leaves (see workers.checkpoint)."""
        state: dict[str, Any] = {"mean": self.memory.mean.copy(), "rng": rng_state(self.rng)}
        if self.memory.elites is not None:
            state["elites"] = self.memory.elites.copy()
        return state

    def load_state_dict(self, state: Mapping[str, Any]) -> None:
        """Continue exactly where :meth:`state_dict` was taken."""
        self.memory = PlannerMemory(
            np.array(state["mean"]), None if "elites" not in state else np.array(state["elites"])
        )
        self.rng = restore_rng(state["rng"])

    # ---------------------------------------------------------- sampling
    def _sample(self, mean: np.ndarray, std: np.ndarray, count: int) -> np.ndarray:
        config = self.config
        if config.bounds == "clip":
            # Colored noise C^beta(d, h): correlations run along time (section 3.2.1).
            noise = colored_noise(
                config.noise_beta, (count, self.action_dim, config.horizon), self.rng, config.noise_release
            )
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

    def _shifted_elites(self, previous: np.ndarray, mean: np.ndarray, std: np.ndarray) -> np.ndarray:
        """Last step's best elites moved one step in time, with a fresh random last action."""
        kept = previous[: self.reused]
        fresh = self._sample(mean, std, len(kept))[:, -1:]
        return np.concatenate([kept[:, 1:], fresh], axis=1)

    @staticmethod
    def _as_batch(result: np.ndarray | CostBatch, count: int) -> CostBatch:
        batch = result if isinstance(result, CostBatch) else CostBatch(np.asarray(result, dtype=np.float64))
        if batch.costs.shape[:1] != (count,) or batch.costs.ndim not in (1, 2):
            raise ValueError(f"cost function returned shape {batch.costs.shape}, expected ({count},) or ({count}, P)")
        for name, values in batch.components.items():
            if np.shape(values) != (count,):
                raise ValueError(f"cost component {name!r} has shape {np.shape(values)}, expected ({count},)")
        return batch

    # ---------------------------------------------------------- planning
    def plan(self, cost_function: CostFunction, proposals: np.ndarray | None = None) -> PlanResult:
        """Optimise the action sequence for the current state; return the action to execute.

        Args:
            cost_function: costs of action sequences from the current state.
            proposals: (M, h, d) candidate sequences that each replace one
                random sample of the last CEM-iteration (after the mean, when
                add-mean is on), so the budget is unchanged (App. C.2).
        """
        config = self.config
        mean = self.memory.mean
        previous_elites = self.memory.elites
        std = self._cap_std(mean, np.full(self.shape, config.sigma_init))  # sigma reset every step
        elites = elite_batch = None
        best_cost, best_sequence, best_components = np.inf, None, {}
        evaluated = 0
        last = config.iterations - 1

        for i, count in enumerate(self.population_sizes):
            samples = self._sample(mean, std, count)
            if i == last:
                extra = [mean[None]] if config.add_mean else []
                # The mean takes the place of one sample (B.4.3: last iteration only), which
                # keeps the budget of Table 4 as in the authors' implementation.
                if proposals is not None and len(proposals):
                    extra.append(np.clip(np.asarray(proposals, dtype=np.float64).reshape(-1, *self.shape), LOW, HIGH))
                if extra:
                    replacements = np.concatenate(extra)[:count]
                    samples[: len(replacements)] = replacements
            if i == 0 and config.shift_elites and previous_elites is not None and self.reused:
                samples = np.concatenate([samples, self._shifted_elites(previous_elites, mean, std)])
            kept = i > 0 and config.keep_elites and self.reused
            if kept and config.reevaluate_elites:
                # A stochastic model's cost of a kept elite is a fresh draw, not its old one.
                samples = np.concatenate([samples, elites[: self.reused]])
            batch = self._as_batch(cost_function(samples), len(samples))
            evaluated += len(samples)
            if kept and not config.reevaluate_elites:
                # Deterministic ground truth: kept elites keep their costs (and cost terms).
                keep = np.arange(self.reused)
                samples = np.concatenate([samples, elites[keep]])
                batch = CostBatch.concatenate(batch, elite_batch.take(keep))

            costs = np.asarray(self.objective(batch, i), dtype=np.float64)
            costs = np.where(np.isfinite(costs), costs, np.inf)
            order = np.argsort(costs, kind="stable")[: config.elites]
            elites, elite_batch = samples[order], batch.take(order)
            final_elites = i == last and config.best_from == "last_iteration"
            # With every cost non-finite (a diverging learned model) the first elite is the best there is.
            if final_elites or best_sequence is None or costs[order[0]] < best_cost:
                best_cost, best_sequence = float(costs[order[0]]), elites[0].copy()
                best_components = {k: float(v[0]) for k, v in elite_batch.components.items()}

            alpha = config.momentum
            mean = alpha * mean + (1 - alpha) * elites.mean(axis=0)
            std = self._cap_std(mean, alpha * std + (1 - alpha) * elites.std(axis=0))

        plan = best_sequence if config.best_action else mean
        action = plan[0].copy()

        # Shift initialisation of the next step's mean (eq. 32-33).
        if config.shift_mean:
            tail = mean[-1:] if config.shift_last == "repeat" else np.zeros((1, self.action_dim))
            next_mean = np.concatenate([mean[1:], tail])
        else:
            next_mean = np.zeros(self.shape)
        self.memory = PlannerMemory(next_mean, elites)
        return PlanResult(action, best_cost, evaluated, plan.copy(), mean.copy(), best_components)
