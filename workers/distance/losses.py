"""Labels of the distance losses (eq. 28-31, Alg. 4) as pure functions of sampled indices and estimates.

Samplers return index sets and the raw inputs; label functions turn
bootstrapped estimates and counts into regression targets and masks. Nothing
here touches a network, so every label can be checked on hand-built numbers.

Index convention: an episode holds states s_0 ... s_T and actions
a_0 ... a_{T-1}. A temporal pair takes i uniform in [0, T - 1] (s_i must have
an action) and j uniform in [i + 1, T] (App. E.3.2 samples i first, then j
after it; we let j reach the final state s_T, which is the state a_{T-1} leads
to). j - i is then the number of steps a_i starts, so d(s_i, a_i, ag(s_{i+1}))
is trained towards 1.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from workers.distance.buffer import EpisodeBuffer, Episodes


class TemporalBatch(NamedTuple):
    """Pairs i < j from single episodes (eq. 31a)."""

    observations: np.ndarray
    """(B, obs_dim) s_i."""
    actions: np.ndarray
    """(B, action_dim) a_i."""
    goals: np.ndarray
    """(B, goal_dim) ag(s_j)."""
    next_observations: np.ndarray
    """(B, obs_dim) s_{i+1} (DDL's d(s, g) is trained on states, not state-actions)."""
    steps: np.ndarray
    """(B,) j - i (>= 1 unless sampled with min_gap 0)."""
    episodes: np.ndarray
    """(B,) buffer slots."""
    first: np.ndarray
    """(B,) i."""
    second: np.ndarray
    """(B,) j."""


def sample_temporal(
    buffer: EpisodeBuffer, batch_size: int, rng: np.random.Generator, min_gap: int = 1
) -> TemporalBatch:
    """Episodes uniform over the buffer, i uniform in [0, T - 1], j uniform in [i + min_gap, T] (App. E.3.2).

    ``min_gap`` 1 for d(s, a, g) (a_i takes at least one step); DDL's
    regression samples j ~ [i, T] (section 6.3.2), so min_gap 0 teaches
    d(s, ag(s)) = 0 as well.
    """
    if buffer.size == 0:
        raise ValueError("cannot sample from an empty buffer")
    if min_gap not in (0, 1):
        raise ValueError(f"min_gap must be 0 or 1, got {min_gap}")
    horizon = buffer.horizon
    episodes = rng.integers(buffer.size, size=batch_size)
    first = rng.integers(horizon, size=batch_size)
    span = horizon + 1 - min_gap - first
    second = first + min_gap + np.floor(rng.random(batch_size) * span).astype(np.int64)
    return TemporalBatch(
        observations=buffer.observations[episodes, first],
        actions=buffer.actions[episodes, first],
        goals=buffer.achieved_goals[episodes, second],
        next_observations=buffer.observations[episodes, first + 1],
        steps=(second - first).astype(np.float64),
        episodes=episodes,
        first=first,
        second=second,
    )


def count_uncertainty(counts: np.ndarray, scale: float = 400.0, exponent: float = 2.0) -> np.ndarray:
    """U = C / (1 + N)^M (eq. 29): C for unseen (s, a), decaying polynomially with visits."""
    return scale / (1.0 + np.asarray(counts, dtype=np.float64)) ** exponent


def temporal_targets(steps: np.ndarray, target_estimates: np.ndarray, uncertainty: np.ndarray) -> np.ndarray:
    """min(j - i, d_old(s_i, a_i, ag(s_j)) + U) (eq. 28 / 31a).

    j - i is an upper bound of the true distance (the episode did it in j - i
    steps); d_old + U replaces it only where the network's shorter estimate is
    backed by enough visits of (s_i, a_i).
    """
    return np.minimum(np.asarray(steps, dtype=np.float64), np.asarray(target_estimates) + np.asarray(uncertainty))


def regression_targets(steps: np.ndarray) -> np.ndarray:
    """DDL's on-policy temporal regression target: j - i (section 6.3.2)."""
    return np.asarray(steps, dtype=np.float64)


class TriangularBatch(NamedTuple):
    """Triples for the triangular loss (eq. 30 / 31b, Alg. 4 lines 11-20)."""

    observations: np.ndarray
    """(B, obs_dim) s_i from a recent episode."""
    actions: np.ndarray
    """(B, action_dim) a_i."""
    goals: np.ndarray
    """(B, goal_dim) g: the desired goal of s_i's episode."""
    via_observations: np.ndarray
    """(B, obs_dim) s_j from anywhere in the buffer D."""
    via_actions: np.ndarray
    """(B, action_dim) a_j."""
    via_goals: np.ndarray
    """(B, goal_dim) ag(s_j), the goal-space end of the first cathetus d(s_i, a_i, ag(s_j))."""


def sample_triangular(
    recent: Episodes, buffer: EpisodeBuffer, batch_size: int, rng: np.random.Generator
) -> TriangularBatch:
    """(s_i, a_i, g) from the recent episodes D_last, (s_j, a_j) uniform over all of D (Alg. 4 lines 12-14)."""
    if len(recent) == 0 or buffer.size == 0:
        raise ValueError("the triangular loss needs recent episodes and a non-empty buffer")
    horizon = buffer.horizon
    own = rng.integers(len(recent), size=batch_size)
    first = rng.integers(horizon, size=batch_size)
    other = rng.integers(buffer.size, size=batch_size)
    second = rng.integers(horizon, size=batch_size)
    return TriangularBatch(
        observations=recent.observations[own, first],
        actions=recent.actions[own, first],
        goals=recent.goals[own],
        via_observations=buffer.observations[other, second],
        via_actions=buffer.actions[other, second],
        via_goals=buffer.achieved_goals[other, second],
    )


def triangular_targets(
    first_leg: np.ndarray,
    second_leg: np.ndarray,
    counts_to_goal: np.ndarray,
    via_counts_to_goal: np.ndarray,
    cap: float | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Targets d_old(s_i, a_i, ag(s_j)) + d_old(s_j, a_j, g) and the mask of samples that train (eq. 31b).

    A sample trains only when g was never reached after (s_i, a_i) but was
    reached after (s_j, a_j): N(s_i, a_i, g) = 0 and N(s_j, a_j, g) > 0
    (Alg. 4 line 15; the sets mu(g) and its complement of eq. 31b). Every other
    sample is left out ("do nothing"). With a ``cap`` the sums are clipped into
    [0, cap] (``DistanceSettings.triangular_target_cap``).
    """
    mask = (np.asarray(counts_to_goal) == 0) & (np.asarray(via_counts_to_goal) > 0)
    targets = np.asarray(first_leg, dtype=np.float64) + np.asarray(second_leg, dtype=np.float64)
    if cap is not None:
        targets = np.clip(targets, 0.0, cap)
    return targets, mask


def merge_and_relax_rates(predictions: np.ndarray, targets: np.ndarray, mask: np.ndarray) -> tuple[float, float]:
    """Fractions of a triangular batch whose hypotenuse the loss raises (merge) or lowers (relax).

    Section 6.6.1 and Fig. 24b / 26: the *merging rate* is the rate "at which
    the distances to the goal get increased", i.e. the hypotenuse d(s_i, a_i, g)
    is pulled up to the sum of the catheti ("at most 30 % of the training batch
    gets penalized"); the *relaxation rate* is the rate at which they are
    "regularized" downwards because a shorter path through s_j was found (the
    Floyd-Warshall relaxation). Both are counted over the whole sampled batch,
    so samples outside the mask count as neither; predictions are the current
    network's, before the update.
    """
    batch = max(1, len(predictions))
    mask = np.asarray(mask, dtype=bool)
    merge = np.count_nonzero(mask & (targets > predictions)) / batch
    relax = np.count_nonzero(mask & (targets < predictions)) / batch
    return float(merge), float(relax)
