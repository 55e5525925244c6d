"""What a trained ensemble believes about one step from each point of a task's plane: Var_A and Var_E.

RAZER steers by the model's uncertainty (section 5.3.5): the aleatoric
penalty (eq. 26) on Var_A, the mean over members of their predicted variance
(eq. 22), and the epistemic bonus (eq. 27) on Var_E, the spread of the
members' predictions (eq. 24). Whether the aleatoric penalty can keep a plan
off BridgeMaze's windy bridge depends on whether the model has learned that
one step there is noisier than one step on the other bridges. This module
evaluates both terms for one step from a grid of states in the task's plane
(:meth:`~workers.tasks.model_based.ModelBasedTask.plane_states` says which
state stands for a point), reduced over dimensions as the planner reduces
them (:func:`~workers.dynamics.costs.reduce_uncertainty`, the trial's
``uncertainty_dims`` and ``uncertainty_reduction``).

One step from a state that all members share, so Var_A here is what a step
adds, not the spread particles build up over a horizon: the per-step summand
of eq. 26 at the start of a plan.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import torch

from workers.dynamics.costs import reduce_uncertainty
from workers.dynamics.ensemble import DynamicsEnsemble
from workers.dynamics.propagation import population_variance
from workers.dynamics.settings import RazerSettings


class UncertaintyMap(NamedTuple):
    """U(Var_A) and U(Var_E) of one step from every grid point of a plane."""

    x: np.ndarray
    """(nx,) grid point x coordinates."""
    y: np.ndarray
    """(ny,) grid point y coordinates."""
    aleatoric: np.ndarray
    """(nx, ny) U(Var_A), eq. 22 reduced as eq. 26 reduces it."""
    epistemic: np.ndarray
    """(nx, ny) U(Var_E), eq. 24 (the trial's ``epistemic_terms``) reduced as eq. 27 reduces it."""


def one_step_uncertainty(
    model: DynamicsEnsemble, states: np.ndarray, actions: np.ndarray, settings: RazerSettings
) -> tuple[np.ndarray, np.ndarray]:
    """(U(Var_A), U(Var_E)) of one step from (B, d) states under (B, d_a) model-space actions, each (B,)."""
    inputs = torch.as_tensor(np.concatenate([states, actions], axis=-1), dtype=torch.float32)
    mean, logvar = model.predict(inputs.expand(model.ensemble_size, -1, -1))
    variance = logvar.exp()
    var_aleatoric = variance.mean(dim=0)  # eq. 22 with every member at the same state
    var_epistemic = population_variance(mean)  # eq. 24
    if settings.epistemic_terms == "means_and_variances":
        var_epistemic = var_epistemic + population_variance(variance)
    reduce = settings.uncertainty_reduction, settings.uncertainty_dims
    return reduce_uncertainty(var_aleatoric, *reduce).numpy(), reduce_uncertainty(var_epistemic, *reduce).numpy()


def uncertainty_map(
    model: DynamicsEnsemble,
    task,
    settings: RazerSettings,
    ranges: tuple[tuple[float, float], tuple[float, float]],
    bins: int = 80,
) -> UncertaintyMap | None:
    """The map over ``ranges`` ((x0, x1), (y0, y1)) at ``bins`` points per axis; None if the task has no plane."""
    x = np.linspace(*ranges[0], bins)
    y = np.linspace(*ranges[1], bins)
    grid_x, grid_y = np.meshgrid(x, y, indexing="ij")
    probe = task.plane_states(np.stack([grid_x.ravel(), grid_y.ravel()], axis=1))
    if probe is None:
        return None
    states, actions = probe
    aleatoric, epistemic = one_step_uncertainty(model, states, actions, settings)
    return UncertaintyMap(x, y, aleatoric.reshape(bins, bins), epistemic.reshape(bins, bins))
