"""The guided cost of APEX (eq. 15-16) and its adaptive weights (eq. 17-18).

f(a) = J(a) + sum_j lambda_j C_j(a), with the auxiliary costs

* C_1 = sum_t ||a_t - pi(s_t)||^2, the guidance (eq. 15: the KL term of a
  deterministic policy), s_t the state predicted along the sample's own
  rollout (s_0 the current state);
* C_2 = sum_t ||a_t||, the action norm (off by default).

The evaluator returns J and every C_j separately (:class:`CostBatch`
components), and :class:`GuidedObjective` weighs them afresh at every
CEM-iteration, kept elites included: a kept elite's stored costs are
re-weighed with the new lambda rather than keeping an earlier f.

Adaptive weights (eq. 17-18): lambda_j = c_j R(J) / (R(C_j) + eps), with
R(X) = max - min of X over the elite set. Eq. 17 is circular (lambda needs
the elite set, the elite set is ranked by f, f needs lambda). Reading used
here, after the text's own words ("if the main cost J cannot be improved by
the *preliminary* elite-set"): at every CEM-iteration the preliminary
elite-set is the K candidates with the lowest main cost J (this iteration's
samples and the kept elites); R(J) and R(C_j) are taken over it (R(J) over
its finite costs); then f ranks
all candidates and selects the elite set that the distribution is refit to.
So lambda is exactly 0 while J is flat among the K best samples (sparse
rewards, nothing found yet), and the auxiliary terms then span at most a
fraction c_j of J's range over those samples.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import numpy as np

from workers.planning.icem import CostBatch

GUIDANCE = "guidance"
"""Name of the cost component C_1 = sum_t ||a_t - pi(s_t)||^2."""
ACTION_NORM = "action_norm"
"""Name of the cost component C_2 = sum_t ||a_t||."""


class AuxiliaryTerm(NamedTuple):
    """One auxiliary cost C_j and how its weight lambda_j is set."""

    name: str
    """The cost component's name (GUIDANCE, ACTION_NORM)."""
    adaptive: bool
    """lambda_j by eq. 17 at every CEM-iteration; otherwise ``fixed``."""
    c: float
    """c_j of eq. 17 (Table 10: 0.025)."""
    fixed: float
    """lambda_j when not adaptive."""


class LambdaRecord(NamedTuple):
    """The weights chosen at one CEM-iteration."""

    iteration: int
    lambdas: dict[str, float]
    """lambda_j per auxiliary term."""
    main_range: float
    """R(J) over the preliminary elite set."""
    main_min: float
    main_max: float


def adaptive_lambda(main: np.ndarray, auxiliary: np.ndarray, c: float, epsilon: float) -> float:
    """Eq. 17: c R(J) / (R(C) + eps), ranges over the given (elite) values."""
    return float(c * np.ptp(main) / (np.ptp(auxiliary) + epsilon))


def preliminary_elites(main: np.ndarray, elites: int) -> np.ndarray:
    """Indices of the ``elites`` candidates with the lowest main cost (ties by position)."""
    finite = np.where(np.isfinite(main), main, np.inf)
    return np.argsort(finite, kind="stable")[: min(elites, len(main))]


class GuidedObjective:
    """Ranks a CEM-iteration's candidates by f = J + sum_j lambda_j C_j (an ``Objective`` of the planner).

    Args:
        elites: K, the size of the (preliminary) elite set.
        terms: the auxiliary costs to weigh in; components missing from a batch count as 0.
        epsilon: eps of eq. 17.

    Every call appends a :class:`LambdaRecord` to :attr:`records`.
    """

    def __init__(self, elites: int, terms: Sequence[AuxiliaryTerm], epsilon: float = 1e-6):
        self.elites = elites
        self.terms = list(terms)
        self.epsilon = epsilon
        self.records: list[LambdaRecord] = []

    @property
    def adaptive(self) -> bool:
        """Whether some weight changes between CEM-iterations."""
        return any(term.adaptive for term in self.terms)

    def __call__(self, batch: CostBatch, iteration: int) -> np.ndarray:
        main = np.asarray(batch.main(), dtype=np.float64)
        prelim = preliminary_elites(main, self.elites)
        # Both ranges of eq. 17 over the same samples: the preliminary elites whose J is finite (a diverged
        # simulation's guidance distance must not widen R(C) and so shrink lambda).
        prelim = prelim[np.isfinite(main[prelim])]
        finite = main[prelim]
        main_range = float(np.ptp(finite)) if len(finite) else 0.0
        cost = main.copy()
        lambdas: dict[str, float] = {}
        for term in self.terms:
            if term.name not in batch.components:
                continue
            values = np.asarray(batch.components[term.name], dtype=np.float64)
            if term.adaptive:
                spread = float(np.ptp(values[prelim])) if len(prelim) else 0.0
                weight = float(term.c * main_range / (spread + self.epsilon))
            else:
                weight = float(term.fixed)
            lambdas[term.name] = weight
            if weight:
                cost = cost + weight * values
        low = float(finite.min()) if len(finite) else float("nan")
        high = float(finite.max()) if len(finite) else float("nan")
        self.records.append(LambdaRecord(iteration, lambdas, main_range, low, high))
        return cost
