"""RAZER's sequence cost: task cost, aleatoric penalty, epistemic bonus, safety penalty.

Eq. 25-27 (section 5.3.5) and eq. 34-35 (App. D.1.3); Alg. 5 line 8:
c_tot = c + c_A + c_E + c_S for every action sequence, with

* c   = sum_t mean_p c(s~^p_{t-1}, a_{t-1}, s~^p_t)            (eq. 25, cost_along_trajectory "sum", Table 15)
* c_A = w_A sum_t U(Var_A(t))                                   (eq. 26)
* c_E = -w_E sum_t U(Var_E(t))                                  (eq. 27)
* c_S = w_S sum_t [p(s_t in C) > delta]                         (eq. 35)

U turns a per-dimension variance into one number. Eq. 26-27 write
sqrt(Var) of a vector without saying how dimensions combine; the default
``sum_sqrt`` sums the per-dimension standard deviations, which keeps every
term in units of the observation (App. D.2.5 prefers variance over entropy
because it is "of the same scale as the observation space").

PETS is w_A = w_E = 0 without mean propagation (section 5.4.1: the only
difference of RAZER is the propagated mean and the penalties).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import numpy as np
import torch

from workers.dynamics.propagation import Propagation, population_variance
from workers.dynamics.settings import MeanPropagation, RazerSettings, SafetyBox, UncertaintyReduction  # noqa: F401

TaskCost = Callable[[torch.Tensor, torch.Tensor, torch.Tensor], torch.Tensor]
"""Per-transition planning cost c(s_t, a_t, s_{t+1}): (B, d), (B, d_a), (B, d) tensors -> (B,)."""


class CostTerms(NamedTuple):
    """Cost terms of N sequences, each (N,); ``total`` = task + aleatoric + epistemic + safety (Alg. 5 line 8)."""

    total: torch.Tensor
    task: torch.Tensor
    """c: mean particle cost summed over the horizon (eq. 25)."""
    aleatoric: torch.Tensor
    """c_A = w_A sum_t U(Var_A) (eq. 26), >= 0."""
    epistemic: torch.Tensor
    """c_E = -w_E sum_t U(Var_E) (eq. 27), <= 0."""
    safety: torch.Tensor
    """c_S = w_S sum_t [p_violation > delta] (eq. 35)."""
    aleatoric_uncertainty: torch.Tensor
    """sum_t U(Var_A), unweighted (for logging)."""
    epistemic_uncertainty: torch.Tensor | None
    """sum_t U(Var_E), unweighted; None without mean propagation."""
    violation_steps: torch.Tensor
    """Number of steps whose violation probability exceeds delta (0 when no boxes are set)."""


def reduce_uncertainty(
    variance: torch.Tensor, reduction: UncertaintyReduction, dims: tuple[int, ...] | None = None
) -> torch.Tensor:
    """(..., d) per-dimension variances -> (...) one uncertainty per step (see the module docstring)."""
    if dims is not None:
        variance = variance[..., list(dims)]
    if reduction == "sum_sqrt":
        return variance.sqrt().sum(dim=-1)
    if reduction == "sqrt_sum":
        return variance.sum(dim=-1).sqrt()
    if reduction == "mean_sqrt":
        return variance.sqrt().mean(dim=-1)
    raise ValueError(f"unknown uncertainty reduction {reduction!r}")


def box_violation_probability(mean: torch.Tensor, std: torch.Tensor, box: SafetyBox) -> torch.Tensor:
    """P(s in box) under N(mean, diag(std^2)) (eq. 34): product over constrained dims of Phi(hi) - Phi(lo).

    ``mean`` and ``std`` are (..., d). A box is exactly the product of its
    per-dimension intervals, so with a diagonal Gaussian eq. 34's product is
    exact. A zero std gives the indicator of the mean lying in the box.
    """
    low, high = box.edges()
    dims = list(box.dims)
    mu, sigma = mean[..., dims], std[..., dims].clamp_min(1e-12)
    inside = torch.special.ndtr((high - mu) / sigma) - torch.special.ndtr((low - mu) / sigma)
    return inside.clamp_min(0.0).prod(dim=-1)


def moment_matched_violation(particles: torch.Tensor, boxes: tuple[SafetyBox, ...]) -> torch.Tensor:
    """(N, P, h, d) particles -> (N, h) max over boxes of the violation probability of the moment-matched Gaussian.

    App. D.1.3: mean and (diagonal) variance are the Monte Carlo moments of the
    sampled particles per time slice; the mean states are not used ("for the
    safety term ideally we want to use the full distribution", D.2.4). The
    variance is the unbiased sample variance (divided by P - 1): with a handful
    of particles (P = 5 by default) the population variance is a fifth too
    small on average and would understate exactly the tail probabilities the
    term tests against delta. One particle has no spread.
    """
    count = particles.shape[1]
    mean = particles.mean(dim=1)
    std = (population_variance(particles, dim=1) * (count / (count - 1) if count > 1 else 0.0)).sqrt()
    probabilities = [box_violation_probability(mean, std, box) for box in boxes]
    return torch.stack(probabilities).amax(dim=0)


def sequence_costs(
    propagation: Propagation, actions: torch.Tensor, task_cost: TaskCost, settings: RazerSettings
) -> CostTerms:
    """RAZER's cost terms of N action sequences from their PETSUS propagation."""
    particles = propagation.particles
    n, p, h, d = particles.shape
    previous = torch.cat([propagation.start.expand(n, p, 1, d), particles[:, :, :-1]], dim=2)
    per_particle_actions = actions.to(particles.dtype).unsqueeze(1).expand(n, p, h, -1)
    cost = task_cost(
        previous.reshape(-1, d), per_particle_actions.reshape(n * p * h, -1), particles.reshape(-1, d)
    ).reshape(n, p, h)
    return particle_cost_terms(cost, particles, propagation.var_aleatoric, propagation.var_epistemic, settings)


def particle_cost_terms(
    costs: torch.Tensor,
    particles: torch.Tensor,
    var_aleatoric: torch.Tensor,
    var_epistemic: torch.Tensor | None,
    settings: RazerSettings,
) -> CostTerms:
    """RAZER's cost terms from per-particle step costs and the uncertainties, however the particles came about.

    Args:
        costs: (N, P, h) task cost of every particle step.
        particles: (N, P, h, d) particle states (the safety term's moments).
        var_aleatoric: (N, h, d) Var_A per step.
        var_epistemic: (N, h, d) Var_E per step, None without mean states.
        settings: the weights and switches.
    """
    task = costs.mean(dim=1).sum(dim=1)

    u_a = reduce_uncertainty(var_aleatoric, settings.uncertainty_reduction, settings.uncertainty_dims)
    aleatoric_uncertainty = u_a.sum(dim=1)
    aleatoric = settings.aleatoric_weight * aleatoric_uncertainty

    epistemic_uncertainty = None
    epistemic = torch.zeros_like(task)
    if var_epistemic is not None:
        u_e = reduce_uncertainty(var_epistemic, settings.uncertainty_reduction, settings.uncertainty_dims)
        epistemic_uncertainty = u_e.sum(dim=1)
        epistemic = -settings.epistemic_weight * epistemic_uncertainty
    elif settings.epistemic_weight > 0:
        raise ValueError("epistemic_weight > 0 but the propagation has no mean states")

    violation_steps = torch.zeros_like(task)
    if settings.safety_boxes:
        probability = moment_matched_violation(particles, settings.safety_boxes)
        violation_steps = (probability > settings.safety_delta).to(task.dtype).sum(dim=1)
    safety = settings.safety_weight * violation_steps

    return CostTerms(
        total=task + aleatoric + epistemic + safety,
        task=task,
        aleatoric=aleatoric,
        epistemic=epistemic,
        safety=safety,
        aleatoric_uncertainty=aleatoric_uncertainty,
        epistemic_uncertainty=epistemic_uncertainty,
        violation_steps=violation_steps,
    )


def terms_as_numpy(terms: CostTerms) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """(total (N,), components) as evaluators hand them to the planner, each (N,) float64.

    Components: ``c`` task cost (eq. 25), ``c_A`` aleatoric penalty (eq. 26), ``c_E`` epistemic bonus
    (eq. 27, <= 0), ``c_S`` safety penalty (eq. 35), ``u_A`` and ``u_E`` the unweighted uncertainty sums
    (``u_E`` only with mean states), and ``violation_steps``. ``total`` = c + c_A + c_E + c_S.
    """
    components = {
        "c": terms.task,
        "c_A": terms.aleatoric,
        "c_E": terms.epistemic,
        "c_S": terms.safety,
        "u_A": terms.aleatoric_uncertainty,
        "violation_steps": terms.violation_steps,
    }
    if terms.epistemic_uncertainty is not None:
        components["u_E"] = terms.epistemic_uncertainty
    as_numpy = {name: value.double().numpy() for name, value in components.items()}
    return terms.total.double().numpy(), as_numpy
