"""PETSUS: trajectory sampling with uncertainty separation (thesis section 5.3.4, eq. 20-24, Fig. 18, App. D.2.4).

For N action sequences and P particles per sequence, every model step is one
batched ensemble evaluation over all N * P particles plus the mean states:

* **Particles (TS1, Chua et al.)**: each particle is sampled from the Gaussian
  of the member it is assigned to, and particles are re-assigned to random
  members at *every* step. The assignment is balanced: at each step, each
  sequence's particles are randomly ranked and dealt to the members like
  cards, the members in a random order. With P a multiple of K every member
  predicts exactly P/K particles of every sequence at every step; otherwise
  loads differ by at most one and the surplus goes to random members. Balance keeps the batch
  rectangular, (K, N ceil(P/K), d), so a step is a single baddbmm per layer.
* **Mean propagation** (no sampling, the yellow lines of Fig. 18), the input of
  the epistemic estimate (eq. 24). ``per_member`` (default): every member
  propagates its own mean state, s_bar^k_{t+1} = s_bar^k_t + mu_k(s_bar^k_t, a_t),
  the reading of App. D.2.4 ("propagates the mean prediction for each ensemble
  member"). ``shared``: one mean state, s_bar_{t+1} = s_bar_t + mean_k mu_k(s_bar_t, a_t),
  on which every member is evaluated, the reading of eq. 24's unindexed s_bar_t.
  ``none``: plain PETS. Both variants cost the same K mean-state rows per sequence.
* **Clamp**: particles and mean states are clamped into the training data's
  range widened by ``EnsembleConfig.state_margin`` (not in the thesis; see there).
* **Projection**: then moved by the task's ``project_states`` (BridgeMaze: the
  quaternion rescaled to unit length), if one is given (not in the thesis; PETS's
  ``obs_postproc``).

Uncertainties, per state dimension:

* Var_A(t+1) = mean over the sequence's particles of the variance the member
  assigned to the particle predicts for it (eq. 22: the mean over members of
  Sigma_k(s~_t, a_t); with balanced TS1 both means coincide for P = multiple of K).
  ``aleatoric_states="means"`` reads it at the mean states instead: the mean over
  members of Sigma_k(s_bar^k_t, a_t) (per_member) or Sigma_k(s_bar_t, a_t) (shared).
  A particle's state carries the noise of every earlier sampled step, so along the
  horizon the particles spread into states the data never covered, where the
  predicted variances are large whatever the route; the mean states do not.
* Var_E(t+1) = Var_k[mu_k(s_bar_t, a_t)] + Var_k[Sigma_k(s_bar_t, a_t)] (eq. 24),
  the empirical (population, divide-by-K) variance over members, taken at each
  member's own mean state in the per_member mode. mu_k is the predicted change, as
  eq. 19 defines it (the mean of the next state is s + mu_k), so this is eq. 24 as
  written; the spread of the next mean states s_bar^k_{t+1} themselves (D.2.4's
  recursion) would also count how far the members' mean states have drifted apart. The second term literally
  adds a variance of variances to a variance of means, as eq. 24 writes it;
  ``epistemic_terms="means"`` keeps the first term only.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import torch

from workers.dynamics.ensemble import DynamicsEnsemble
from workers.dynamics.settings import AleatoricStates, EpistemicTerms, MeanPropagation


class Propagation(NamedTuple):
    """The predicted trajectory distribution of N action sequences (torch tensors)."""

    start: torch.Tensor
    """(d,) the state every sequence starts from."""
    particles: torch.Tensor
    """(N, P, h, d) sampled particle states s~_1 ... s~_h."""
    members: torch.Tensor
    """(N, P, h) the member that predicted each particle state (TS1 assignment)."""
    var_aleatoric: torch.Tensor
    """(N, h, d) Var_A of eq. 22 for steps 1 ... h."""
    means: torch.Tensor | None
    """(M, N, h, d) propagated mean states (M = K per member, 1 shared); None without mean propagation."""
    var_epistemic: torch.Tensor | None
    """(N, h, d) Var_E of eq. 24 for steps 1 ... h; None without mean propagation."""


def population_variance(x: torch.Tensor, dim: int = 0) -> torch.Tensor:
    """Variance over ``dim``, dividing by its size; ``Tensor.var`` takes a slow path on CPU for this
    reduction (about 10x slower on (K, N, d) member predictions)."""
    centred = x - x.mean(dim=dim, keepdim=True)
    return centred.square().mean(dim=dim)


def petsus_propagate(
    model: DynamicsEnsemble,
    start: torch.Tensor,
    actions: torch.Tensor,
    particles: int,
    mean_propagation: MeanPropagation = "per_member",
    generator: torch.Generator | None = None,
    epistemic_terms: EpistemicTerms = "means_and_variances",
    project: Callable[[torch.Tensor], torch.Tensor] | None = None,
    aleatoric_states: AleatoricStates = "particles",
) -> Propagation:
    """Propagate P TS1 particles (and the mean states) of N action sequences through the ensemble.

    Args:
        model: the ensemble.
        start: (d,) start state.
        actions: (N, h, d_a) action sequences, as the model was trained on them.
        particles: P, particles per sequence.
        mean_propagation: ``per_member``, ``shared`` or ``none`` (see the module docstring).
        generator: torch generator for the particle noise and the TS1 assignment.
        epistemic_terms: what Var_E sums (see :class:`~workers.dynamics.settings.RazerSettings`).
        project: the task's ``project_states``, applied to every particle and mean state after the clamp.
        aleatoric_states: where Var_A is read, ``particles`` (eq. 22) or ``means`` (see the module docstring).
    """
    if particles < 1:
        raise ValueError(f"particles must be at least 1, got {particles}")
    if aleatoric_states == "means" and mean_propagation == "none":
        raise ValueError("Var_A at the mean states needs mean propagation (per_member or shared)")

    def settle(states: torch.Tensor) -> torch.Tensor:
        clamped = model.clamp_states(states)
        return clamped if project is None else project(clamped)

    n, horizon, _ = actions.shape
    k, d = model.ensemble_size, model.obs_dim
    per = -(-particles // k)  # particles per member and sequence, rounded up
    slots_total = per * k
    start = start.to(torch.float32).reshape(d)
    actions = actions.to(torch.float32)
    rows = n * per  # particle rows per member
    if mean_propagation == "per_member":
        mean_state = start.expand(k, n, d).clone()
    elif mean_propagation == "shared":
        mean_state = start.expand(1, n, d).clone()
    elif mean_propagation == "none":
        mean_state = None
    else:
        raise ValueError(f"unknown mean_propagation {mean_propagation!r}")

    # All random draws and index maps of the rollout at once: the loop below is a few dozen tensor operations
    # per step, and for small networks their count, not the matmuls, bounds the throughput.
    # TS1: particle of random rank r takes row r // K of member sigma(r % K), sigma a random permutation
    # of the members: loads are balanced and the surplus of P % K lands on random members.
    rank = torch.rand(horizon, n, particles, generator=generator).argsort(dim=-1)
    sigma = torch.rand(horizon, n, k, generator=generator).argsort(dim=-1)
    slots = (rank // k) * k + sigma.gather(2, rank % k)  # (h, N, P): slot s -> member s % K, row s // K
    noise = torch.randn(horizon, k, rows, d, generator=generator)
    # Particle states live in a flat (N P + 1, d) table whose last row stays 0 (the input of unused slots).
    # gather_rows[t] lists the table rows that make up the member batch at step t (K x N ceil(P/K) rows,
    # member-major); scatter_rows[t] lists where each particle's prediction sits in that batch, flattened.
    sequence = torch.arange(n).view(1, n, 1)
    # owner[t, i, s]: the particle of sequence i in slot s at step t (P: the slot is unused).
    owner = torch.full((horizon, n, slots_total), particles).scatter_(
        2, slots, torch.arange(particles).expand(horizon, n, particles)
    )
    gather_rows = torch.where(owner < particles, sequence * particles + owner, n * particles)
    gather_rows = gather_rows.view(horizon, n, per, k).permute(0, 3, 1, 2).reshape(horizon, k * rows)
    scatter_rows = ((slots % k) * rows + sequence * per + slots // k).view(horizon, n * particles)
    table = torch.zeros(n * particles + 1, d)
    table[:-1] = start
    step_actions = actions.transpose(0, 1)  # (h, N, d_a)
    particle_actions = step_actions.unsqueeze(2).expand(-1, -1, per, -1).reshape(horizon, 1, rows, -1)

    states, var_a, means, var_e = [], [], [], []
    for t in range(horizon):
        particle_in = table.index_select(0, gather_rows[t]).view(k, rows, d)
        state_in, action_in = particle_in, particle_actions[t].expand(k, -1, -1)
        if mean_state is not None:
            state_in = torch.cat([particle_in, mean_state.expand(k, n, d)], dim=1)
            action_in = torch.cat([action_in, step_actions[t].expand(k, n, -1)], dim=1)
        mu, logvar = model.predict(torch.cat([state_in, action_in], dim=-1))  # particles and means in one batch

        var = logvar[:, :rows].exp()
        sampled = settle(particle_in + mu[:, :rows] + var.sqrt() * noise[t])
        torch.index_select(sampled.view(k * rows, d), 0, scatter_rows[t], out=table[:-1])
        states.append(table[:-1].view(n, particles, d).clone())
        if aleatoric_states == "particles":
            var_a.append(var.view(k * rows, d).index_select(0, scatter_rows[t]).view(n, particles, d).mean(dim=1))

        if mean_state is not None:
            mean_mu, mean_var = mu[:, rows:], logvar[:, rows:].exp()  # (K, N, d)
            if aleatoric_states == "means":
                var_a.append(mean_var.mean(dim=0))
            spread = population_variance(mean_mu)
            var_e.append(spread + population_variance(mean_var) if epistemic_terms == "means_and_variances" else spread)
            step = mean_mu if mean_propagation == "per_member" else mean_mu.mean(dim=0, keepdim=True)
            mean_state = settle(mean_state + step)
            means.append(mean_state)

    return Propagation(
        start=start,
        particles=torch.stack(states, dim=2),
        members=(slots % k).permute(1, 2, 0),
        var_aleatoric=torch.stack(var_a, dim=1),
        means=torch.stack(means, dim=2) if means else None,
        var_epistemic=torch.stack(var_e, dim=1) if var_e else None,
    )
