"""Hash count models N(s, a) and N(s, a, g') (thesis App. E.1, Alg. 6).

**Hashing.** A continuous input x (length n) maps to an integer code vector
phi(x) = floor((M x + v) / sigma) with M a k x n matrix of standard normals
and v ~ U[0, sigma)^k (App. E.1; the rounding variant of SimHash after
Datar et al., so collisions follow Euclidean distance). One component of two
inputs at distance r collides with probability E[max(0, 1 - |Z| r / sigma)],
Z ~ N(0, 1); the k components are independent, so whole codes collide with
that probability to the power k (see :func:`code_collision_probability`).

**Counting.** A count-min sketch with one table per prime p_j of App. E.1
(the six published moduli) stores counts of code vectors; a query returns the
minimum over rows, which never undercounts.

**Keys (a deliberate departure).** The authors' reference (the static hashing
of Tang et al., openai/EPG ``exploration.py``) reduces a code vector to a row
key by weighting component l with 2^l mod p_j. That was built for +-1 SimHash
codes; for integer codes it collides systematically: codes (2, 0) and (0, 1)
get the same key in every row, so the minimum over rows cannot remove the
error. We use a Carter-Wegman universal hash per row instead,
key_j(c) = (sum_l a_jl (c_l mod p_j) + b_j) mod p_j with a_jl uniform in
[1, p_j) and b_j uniform in [0, p_j), drawn from the seed. Two code vectors
that differ modulo p_j share a row key with probability 1 / p_j, independently
across rows (codes are far below p_j in magnitude, so "differ modulo p_j" is
"differ").

**Pairs.** N(s, a, g') counts (s_i, a_i, ag(s_j)) for every i < j of an
episode (Alg. 6 line 10, O(T^2) pairs; the third argument is a goal-space
vector, see the SPEC reading notes). The projection of a pair splits as
M [s; a; g] = M_sa [s; a] + M_g g, so an episode needs T + (T + 1) projections,
and the T (T + 1) / 2 pair codes are sums of rows, built at once.

Inputs are rounded to float32 (the replay buffers' precision) before hashing,
so an input hashes the same whether it comes from a collector or a buffer.
"""

from __future__ import annotations

import numpy as np
from scipy.special import ndtr

from workers.distance.buffer import Episodes
from workers.distance.config import SKETCH_MODULI, CountSettings
from workers.distance.state import State, with_prefix

COUNT_DTYPE = np.uint32
"""Counter type of the sketch tables: 24 MB per sketch of six ~1e6 rows (int64 would double it)."""
COUNT_LIMIT = np.iinfo(COUNT_DTYPE).max


def _as_float64(x: np.ndarray) -> np.ndarray:
    return np.asarray(x, dtype=np.float32).astype(np.float64)


def _project(x: np.ndarray, matrix: np.ndarray) -> np.ndarray:
    """x @ matrix.T as an explicit row-wise product sum.

    BLAS matrix products may round differently for different batch sizes; this
    sum gives every row the same bits however many rows are projected together,
    so a pair hashed while counting hashes identically when queried.
    """
    x = _as_float64(x)
    return (x[..., None, :] * matrix).sum(axis=-1)


class RandomProjectionHash:
    """phi(x) = floor((M x + v) / sigma) with M ~ N(0, 1)^{k x n}, v ~ U[0, sigma)^k (App. E.1).

    Args:
        input_dim: n.
        key_dim: k.
        sigma: bucket width.
        rng: source of M and v.
    """

    def __init__(self, input_dim: int, key_dim: int, sigma: float, rng: np.random.Generator):
        if key_dim < 1:
            raise ValueError(f"hash key dimension must be >= 1, got {key_dim}")
        if not sigma > 0:
            raise ValueError(f"hash bucket width sigma must be > 0, got {sigma}")
        self.input_dim, self.key_dim, self.sigma = input_dim, key_dim, float(sigma)
        self.matrix = rng.standard_normal((key_dim, input_dim))
        self.offset = rng.uniform(0.0, sigma, key_dim)

    def project(self, x: np.ndarray) -> np.ndarray:
        """M x for a batch (..., n) -> (..., k)."""
        return _project(x, self.matrix)

    def codes_from_projection(self, projection: np.ndarray) -> np.ndarray:
        """floor((M x + v) / sigma) from M x, as int64."""
        return np.floor((projection + self.offset) / self.sigma).astype(np.int64)

    def codes(self, x: np.ndarray) -> np.ndarray:
        """phi(x) for a batch (..., n) -> (..., k) int64."""
        return self.codes_from_projection(self.project(x))


def code_collision_probability(distance: float | np.ndarray, sigma: float, key_dim: int) -> np.ndarray:
    """Probability that two inputs at Euclidean distance r share all k code components.

    Per component, the projected difference is r Z with Z ~ N(0, 1), and with a
    uniform offset the two land in one bucket with probability
    max(0, 1 - r |Z| / sigma); its expectation is
    2 Phi(1/c) - 1 - 2 c (phi(0) - phi(1/c)) with c = r / sigma.
    """
    c = np.asarray(distance, dtype=np.float64) / sigma
    safe = np.maximum(c, 1e-12)
    u = 1.0 / safe
    pdf_zero = 1.0 / np.sqrt(2.0 * np.pi)
    pdf_u = pdf_zero * np.exp(-0.5 * np.minimum(u, 1e6) ** 2)
    per_component = np.where(c > 0, 2.0 * ndtr(u) - 1.0 - 2.0 * safe * (pdf_zero - pdf_u), 1.0)
    return per_component**key_dim


def collision_radius(sigma: float, key_dim: int, probability: float = 0.5) -> float:
    """Input distance at which two inputs share their whole code with the given probability.

    The scale at which a count model tells inputs apart, in the raw units of
    its input (App. E.1 hashes without preprocessing). About
    sigma ln(1/p) / (0.8 k) for small distances: Table 20's Fetch values
    (sigma 0.3, k 128) give 0.002, so N(s, a) and N(s, a, g') there count
    near-exact repeats only; Point Maze's (sigma 20, k 32) give about 0.5.
    """
    low, high = 0.0, sigma
    while code_collision_probability(high, sigma, key_dim) > probability:
        high *= 2
    for _ in range(60):
        middle = (low + high) / 2
        if code_collision_probability(middle, sigma, key_dim) > probability:
            low = middle
        else:
            high = middle
    return (low + high) / 2


class CountMinSketch:
    """Count-min sketch over integer code vectors with universal-hash row keys.

    Args:
        key_dim: length k of the code vectors.
        rng: source of the per-row multipliers and offsets.
        moduli: one prime per row (App. E.1's six by default).
    """

    def __init__(self, key_dim: int, rng: np.random.Generator, moduli: tuple[int, ...] = SKETCH_MODULI):
        self.key_dim = key_dim
        self.moduli = np.asarray(moduli, dtype=np.int64)
        self.multipliers = np.stack([rng.integers(1, p, key_dim) for p in self.moduli]).astype(np.int64)
        self.offsets = np.array([rng.integers(0, p) for p in self.moduli], dtype=np.int64)
        self.tables = np.zeros((len(self.moduli), int(self.moduli.max())), dtype=COUNT_DTYPE)
        self.total = 0

    def keys(self, codes: np.ndarray) -> np.ndarray:
        """Row keys (N, rows) of code vectors (N, k)."""
        codes = np.asarray(codes, dtype=np.int64).reshape(-1, self.key_dim)
        keys = np.empty((len(codes), len(self.moduli)), dtype=np.int64)
        for row, p in enumerate(self.moduli):
            # Residues and multipliers are < 2^20: each product < 2^40 and the sum of k of
            # them, reduced first, stays far inside int64.
            products = (np.mod(codes, p) * self.multipliers[row]) % p
            keys[:, row] = (products.sum(axis=1) + self.offsets[row]) % p
        return keys

    def add(self, codes: np.ndarray) -> None:
        """Count every code vector once (repeats count repeatedly)."""
        keys = self.keys(codes)
        if self.total + len(keys) > COUNT_LIMIT:
            raise OverflowError(f"count sketch would pass {COUNT_LIMIT} increments; a cell could wrap around")
        for row in range(len(self.moduli)):
            np.add.at(self.tables[row], keys[:, row], 1)
        self.total += len(keys)

    def query(self, codes: np.ndarray) -> np.ndarray:
        """Estimated counts (N,): the minimum over rows, never below the true count."""
        keys = self.keys(codes)
        return self.tables[np.arange(len(self.moduli))[None, :], keys].min(axis=1).astype(np.int64)

    def state(self) -> State:
        """The counters, in whichever form is smaller: the non-zero cells, or the whole tables.

        The tables are ~6e6 counters (24 MB). Early on most are empty and the
        state lists the non-zero cells (a flat uint32 index and the value, 8
        bytes each); the pair sketch of a long run fills so many cells that
        the tables themselves are smaller. Trials checkpoint this every round.
        """
        arrays = {"multipliers": self.multipliers.copy(), "offsets": self.offsets.copy(), "moduli": self.moduli.copy()}
        flat = np.flatnonzero(self.tables)
        if 8 * len(flat) < self.tables.nbytes:
            arrays["cells"] = flat.astype(np.uint32)  # 6 rows x ~1e6 cells < 2^32
            arrays["values"] = self.tables.reshape(-1)[flat].copy()
        else:
            arrays["tables"] = self.tables.copy()
        return State(arrays, {"total": self.total})

    def load(self, state: State) -> None:
        """Restore a sketch exported by :meth:`state` (same moduli)."""
        if not np.array_equal(state.arrays["moduli"], self.moduli):
            raise ValueError("sketch state was made with other moduli")
        self.multipliers = np.array(state.arrays["multipliers"], dtype=np.int64)
        self.offsets = np.array(state.arrays["offsets"], dtype=np.int64)
        if "tables" in state.arrays:
            self.tables[:] = state.arrays["tables"]
        else:
            self.tables[:] = 0
            self.tables.reshape(-1)[np.asarray(state.arrays["cells"], dtype=np.int64)] = state.arrays["values"]
        self.total = int(state.meta["total"])


class StateActionCounts:
    """N(s, a): visits of every (s_t, a_t) of the collected episodes (Alg. 6 lines 5-7).

    Args:
        obs_dim, action_dim: input sizes (the hash sees [s; a]).
        key_dim, sigma: hash parameters (Table 20, left column).
        rng: source of the projection and the sketch's row hashes.
        moduli: count-min primes.
    """

    def __init__(
        self,
        obs_dim: int,
        action_dim: int,
        key_dim: int,
        sigma: float,
        rng: np.random.Generator,
        moduli: tuple[int, ...] = SKETCH_MODULI,
    ):
        self.hash = RandomProjectionHash(obs_dim + action_dim, key_dim, sigma, rng)
        self.sketch = CountMinSketch(key_dim, rng, moduli)

    def codes(self, observations: np.ndarray, actions: np.ndarray) -> np.ndarray:
        return self.hash.codes(np.concatenate([_as_float64(observations), _as_float64(actions)], axis=-1))

    def add(self, observations: np.ndarray, actions: np.ndarray) -> None:
        """Count a batch of (s, a)."""
        self.sketch.add(self.codes(observations, actions))

    def add_episodes(self, episodes: Episodes) -> None:
        """Count every step t < T of every episode."""
        obs = episodes.observations[:, :-1].reshape(-1, episodes.observations.shape[-1])
        self.add(obs, episodes.actions.reshape(-1, episodes.actions.shape[-1]))

    def query(self, observations: np.ndarray, actions: np.ndarray) -> np.ndarray:
        """N(s, a) for a batch, (N,) int64."""
        return self.sketch.query(self.codes(observations, actions))

    def state(self) -> State:
        sketch = self.sketch.state()
        arrays = {"matrix": self.hash.matrix.copy(), "offset": self.hash.offset.copy()}
        arrays.update({f"sketch/{key}": value for key, value in sketch.arrays.items()})
        return State(arrays, {"sketch": sketch.meta})

    def load(self, state: State) -> None:
        self.hash.matrix = np.array(state.arrays["matrix"])
        self.hash.offset = np.array(state.arrays["offset"])
        self.sketch.load(State(with_prefix(state.arrays, "sketch/"), state.meta["sketch"]))


class PairCounts(StateActionCounts):
    """N(s, a, g'): how often goal g' was achieved after taking a in s (Alg. 6 lines 8-10).

    Every pair i < j of an episode counts (s_i, a_i, ag(s_j)), j running up to
    T (the state after the last action), so T (T + 1) / 2 pairs per episode.
    """

    def __init__(
        self,
        obs_dim: int,
        action_dim: int,
        goal_dim: int,
        key_dim: int,
        sigma: float,
        rng: np.random.Generator,
        moduli: tuple[int, ...] = SKETCH_MODULI,
    ):
        self.hash = RandomProjectionHash(obs_dim + action_dim + goal_dim, key_dim, sigma, rng)
        self.sketch = CountMinSketch(key_dim, rng, moduli)
        self.state_action_dim = obs_dim + action_dim

    def _project_state_action(self, observations: np.ndarray, actions: np.ndarray) -> np.ndarray:
        x = np.concatenate([_as_float64(observations), _as_float64(actions)], axis=-1)
        return _project(x, self.hash.matrix[:, : self.state_action_dim])

    def _project_goal(self, goals: np.ndarray) -> np.ndarray:
        return _project(goals, self.hash.matrix[:, self.state_action_dim :])

    def pair_codes(self, observations: np.ndarray, actions: np.ndarray, goals: np.ndarray) -> np.ndarray:
        """phi([s; a; g]) for a batch of triples, (N, k)."""
        projection = self._project_state_action(observations, actions) + self._project_goal(goals)
        return self.hash.codes_from_projection(projection)

    def episode_pair_codes(self, observations: np.ndarray, actions: np.ndarray, achieved: np.ndarray) -> np.ndarray:
        """Codes of all (s_i, a_i, ag(s_j)), i < j <= T, of one episode: (T (T + 1) / 2, k)."""
        horizon = len(actions)
        state_action = self._project_state_action(observations[:horizon], actions)  # (T, k)
        goal = self._project_goal(achieved)  # (T + 1, k)
        first, second = np.triu_indices(horizon, k=1, m=horizon + 1)
        return self.hash.codes_from_projection(state_action[first] + goal[second])

    def add_episodes(self, episodes: Episodes) -> None:
        """Count every pair i < j of every episode (one vectorised block per episode)."""
        for e in range(len(episodes)):
            codes = self.episode_pair_codes(episodes.observations[e], episodes.actions[e], episodes.achieved_goals[e])
            self.sketch.add(codes)

    def query(  # type: ignore[override]
        self, observations: np.ndarray, actions: np.ndarray, goals: np.ndarray
    ) -> np.ndarray:
        """N(s, a, g) for a batch, (N,) int64."""
        return self.sketch.query(self.pair_codes(observations, actions, goals))


class CountModels:
    """The two count models of Alg. 6, seeded together.

    Args:
        settings: hash sizes and sigma (Table 20).
        obs_dim, action_dim, goal_dim: input sizes.
        seed: every random draw (projections, offsets, row hashes) comes from it.
    """

    def __init__(self, settings: CountSettings, obs_dim: int, action_dim: int, goal_dim: int, seed: int):
        rng = np.random.default_rng(seed)
        self.settings = settings
        self.single = StateActionCounts(
            obs_dim, action_dim, settings.single_key_dim, settings.sigma, rng, tuple(settings.moduli)
        )
        self.pair = PairCounts(
            obs_dim, action_dim, goal_dim, settings.pair_key_dim, settings.sigma, rng, tuple(settings.moduli)
        )

    def update(self, episodes: Episodes, pairs: bool = True) -> None:
        """Alg. 6 for the most recent episodes; ``pairs=False`` skips N(s, a, g') (no triangular loss)."""
        self.single.add_episodes(episodes)
        if pairs:
            self.pair.add_episodes(episodes)

    def state(self) -> State:
        single, pair = self.single.state(), self.pair.state()
        arrays = {f"single/{k}": v for k, v in single.arrays.items()} | {f"pair/{k}": v for k, v in pair.arrays.items()}
        return State(arrays, {"single": single.meta, "pair": pair.meta})

    def load(self, state: State) -> None:
        for name, model in (("single", self.single), ("pair", self.pair)):
            prefix = f"{name}/"
            model.load(State(with_prefix(state.arrays, prefix), state.meta[name]))
