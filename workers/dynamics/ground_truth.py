"""An ensemble of noisy ground-truth simulators as the planner's model (thesis App. D.4, Noisy-FetchPickAndPlace).

"We performed the experiments without the learned model, using instead an
ensemble of noisy ground truth dynamics ... This noise is applied to all the
ground truth models of the ensemble, and to the environment as well." Every
action sequence is simulated as P particles, each a MuJoCo rollout of the
task's ground truth from the real environment's state with its own draws of
the task's noise process (:meth:`GroundTruthTask.noisy_actions`); all N x P
rollouts are one batch of the native evaluator (workers/rollout.py).

The members are identical, so the epistemic variance is zero and there are no
mean states; the aleatoric variance Var_A of a step is the spread of the
particles' observations (population variance over the P particles) in the
configured dimensions (by default the task's ``uncertainty_dims``: the box
position on Noisy-FetchPickAndPlace). A simulator has no one-step predicted
variance (eq. 22's Sigma_k), so this is the spread the noise has built up by
step t, not the spread one step adds: noise that scatters the particles early
(a box dropped in some of them) counts again at every later step of the
horizon, so a risk taken early weighs more than the same risk late. The cost terms are RAZER's
(workers/dynamics/costs.py) with the task's own per-step planning costs as the
particle costs; PETS is w_A = 0, the mean particle cost.

Draws are a function of the planning state: :class:`StateDraws` seeds them
from (seed, a digest of the simulator state, the count of draws made since
the planner came to that state), so an evaluation is reproducible, the same whether one process
simulates a batch or several share it, and an MPC episode resumed from a
checkpoint draws what the uninterrupted one drew.
"""

from __future__ import annotations

import hashlib

import numpy as np
import torch

from workers.dynamics.costs import CostTerms, particle_cost_terms, terms_as_numpy
from workers.dynamics.settings import RazerSettings
from workers.rollout import BatchEvaluator
from workers.tasks.base import SimState

PLANNER_STREAM = 0x5A52
"""Tags the planners' draws (the real environment draws from streams of its own)."""


class StateDraws:
    """Standard-normal draws for the particles of N sequences, keyed by the state they start from.

    Args:
        seed: the trial's seed.
        particles: P, particles per sequence.
        noise_dim: draws per particle and step (the task's ``noise_dim``).
    """

    def __init__(self, seed: int, particles: int, noise_dim: int):
        self.seed, self.particles, self.noise_dim = int(seed), int(particles), int(noise_dim)
        self._key: bytes | None = None
        self._calls = 0

    def __call__(self, state: SimState, sequences: int, horizon: int) -> np.ndarray:
        """(N, P, h, noise_dim) draws; the k-th of consecutive calls at one state gives the same values every time
        (the count starts over whenever the state changes: a planner never returns to an earlier state)."""
        parts = [state.physics, state.mocap_pos, state.mocap_quat, state.goal if state.goal is not None else ()]
        key = hashlib.blake2b(b"".join(np.asarray(p, np.float64).tobytes() for p in parts), digest_size=8).digest()
        if key != self._key:
            self._key, self._calls = key, 0
        entropy = [PLANNER_STREAM, self.seed, *np.frombuffer(key, dtype=np.uint32).tolist(), self._calls]
        self._calls += 1
        shape = (sequences, self.particles, horizon, self.noise_dim)
        return np.random.default_rng(entropy).standard_normal(shape)


class GroundTruthEnsembleEvaluator:
    """RAZER / PETS costs of action sequences under P noisy ground-truth rollouts each.

    Same contract as :meth:`EnsembleEvaluator.costs <workers.dynamics.evaluator.EnsembleEvaluator.costs>`,
    from a simulator state instead of an observation.

    Args:
        simulator: the task's native batch evaluator.
        settings: weights and switches (default: PETS); ``uncertainty_dims`` None takes the task's own.
            Mean propagation does not apply (identical members), epistemic and safety weights must be 0.
        particles: P, noisy rollouts per sequence.
        seed: seeds the particles' draws (see :class:`StateDraws`).
    """

    def __init__(
        self, simulator: BatchEvaluator, settings: RazerSettings | None = None, particles: int = 5, seed: int = 0
    ):
        task = simulator.task
        if particles < 1:
            raise ValueError(f"particles must be at least 1, got {particles}")
        if not task.batch_observations:
            raise ValueError(f"{task.name} computes no observations of simulated batches, which Var_A is taken of")
        settings = settings or RazerSettings.pets()
        if settings.epistemic_weight > 0 or settings.safety_weight > 0 or settings.safety_boxes:
            raise ValueError("an ensemble of identical ground-truth members has no epistemic term or safety sets here")
        if settings.uncertainty_dims is None and task.uncertainty_dims is not None:
            settings = settings.model_copy(update={"uncertainty_dims": tuple(task.uncertainty_dims)})
        dims = settings.uncertainty_dims or ()
        if task.observation_dim is not None and any(d >= task.observation_dim for d in dims):
            raise ValueError(f"uncertainty_dims {list(dims)} reach beyond {task.name}'s {task.observation_dim}-d state")
        self.simulator, self.task, self.settings, self.particles = simulator, task, settings, particles
        self.draws = StateDraws(seed, particles, task.noise_dim)

    def terms(self, state: SimState, actions: np.ndarray, draws: np.ndarray | None = None) -> CostTerms:
        """All cost terms (torch, float64) of (N, h, d) sequences; ``draws`` (N, P, h, noise_dim) or drawn here."""
        actions = np.asarray(actions, dtype=np.float64)
        n, horizon, _ = actions.shape
        p = self.particles
        if self.task.noise_dim:
            draws = self.draws(state, n, horizon) if draws is None else np.asarray(draws, dtype=np.float64)
            if draws.shape != (n, p, horizon, self.task.noise_dim):
                raise ValueError(f"draws must be {(n, p, horizon, self.task.noise_dim)}, got shape {draws.shape}")
            flat_draws = draws.reshape(n * p, horizon, self.task.noise_dim)
        else:
            flat_draws = None  # deterministic dynamics: every particle is the same rollout
        # Particles of sequence i are rows i * P ... i * P + P - 1 of one batch.
        batch = self.simulator.simulate(state, np.repeat(actions, p, axis=0), draws=flat_draws)
        model = self.simulator.model
        costs = self.task.costs(model, batch).reshape(n, p, horizon)
        observations = self.task.observations(model, batch).reshape(n, p, horizon, -1)
        variance = observations.var(axis=1)  # population variance over the particles, (N, h, d)
        return particle_cost_terms(
            torch.from_numpy(costs), torch.from_numpy(observations), torch.from_numpy(variance), None, self.settings
        )

    def costs(
        self, state: SimState, actions: np.ndarray, draws: np.ndarray | None = None
    ) -> tuple[np.ndarray, dict[str, np.ndarray]]:
        """(total (N,), components) for (N, h, d) action sequences from ``state``.

        Components as :func:`~workers.dynamics.costs.terms_as_numpy`: ``c`` (mean particle cost summed over
        the horizon), ``c_A`` = w_A ``u_A``, ``c_E`` and ``c_S`` (0 here), ``u_A`` = sum_t U(Var_A),
        ``violation_steps``.
        """
        return terms_as_numpy(self.terms(state, actions, draws))
