"""Settings of neural APSP and its baselines (thesis chapter 6, appendix E.3).

Three settings models, one per separable part, so the service can place each
part on its own actor: :class:`CountSettings` (the hash count models of
App. E.1), :class:`DistanceSettings` (the distance network and its losses,
section 6.5 and Table 20) and :class:`LearnerSettings` (SAC / DDPG + HER,
Table 19). :func:`method_settings` fills them per method and task from the
thesis tables.

Every value is validated where it is defined, so a sweep that sets a hash size
of 0, a non-positive sigma or a negative HER k fails with a message naming the
field.
"""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

Method = Literal["sparse_her", "ddl_her", "offpolicy_ddl_her", "ours_her"]
"""The four rewards of section 6.6: Sparse+HER, DDL+HER, Off-policy DDL+HER, Ours+HER (neural APSP)."""

METHODS: tuple[str, ...] = ("sparse_her", "ddl_her", "offpolicy_ddl_her", "ours_her")

# App. E.1: the moduli of the six count-min rows, "fixed for all the experiments".
SKETCH_MODULI: tuple[int, ...] = (999931, 999953, 999959, 999961, 999979, 999983)


class CountSettings(BaseModel):
    """Hash count models N(s, a) and N(s, a, g') (App. E.1, Alg. 6, Table 20 right)."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False, frozen=True, use_attribute_docstrings=True)

    single_key_dim: int = Field(64, ge=1)
    """Hash key dimension k of N(s, a), used by the temporal loss's uncertainty (Table 20, left column)."""
    pair_key_dim: int = Field(32, ge=1)
    """Hash key dimension k of N(s, a, g'), used by the triangular loss (Table 20, right column)."""
    sigma: float = Field(20.0, gt=0)
    """Bucket width sigma of phi(x) = floor((M x + v) / sigma), v ~ U[0, sigma)^k (Table 20)."""
    moduli: tuple[int, ...] = Field(SKETCH_MODULI, min_length=1)
    """Primes p_j of the count-min rows; the published six by default (App. E.1)."""

    @model_validator(mode="after")
    def _moduli_are_usable(self) -> CountSettings:
        # Keys are computed in int64 as sums of k products of two residues: p^2 k must stay below 2^63.
        for p in self.moduli:
            if p < 2 or p * p * max(self.single_key_dim, self.pair_key_dim) >= 2**62:
                raise ValueError(f"count-min modulus {p} must be >= 2 and small enough for int64 keys")
        return self


class DistanceSettings(BaseModel):
    """The learned distance and its losses (sections 6.3.2-6.5, App. E.3.2, Table 20 left)."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False, frozen=True, use_attribute_docstrings=True)

    conditioning: Literal["state_action", "state"] = "state_action"
    """d(s, a, g) (off-policy, eq. 28) or d(s, g) (DDL, the temporal regression of section 6.3.2)."""
    temporal: Literal["off_policy", "regression"] = "off_policy"
    """Temporal target: min(j - i, d_old + U) (eq. 31a) or plain j - i (DDL)."""
    triangular: bool = True
    """Train the triangular loss (eq. 31b) after the temporal phase (Ours+HER only)."""
    hidden: tuple[int, ...] = Field((256, 256, 256), min_length=1)
    """Hidden layer widths, ReLU (Table 20: 3 x 256; DDL 2 x 256 on Point Maze)."""
    learning_rate: float = Field(3e-4, gt=0)
    """Adam learning rate (Table 20)."""
    batch_size: int = Field(256, ge=1)
    """Samples per distance update (Table 20)."""
    buffer_size: int = Field(1_000_000, ge=1)
    """Transitions kept by the distance trainer's replay buffer D (Table 20: 1e6; DDL 1e5)."""
    temporal_updates_per_episode: int = Field(100, ge=0)
    """Temporal-loss updates per collected episode (Table 20, "updates per episode")."""
    triangular_updates_per_episode: int = Field(100, ge=0)
    """Triangular-loss updates per collected episode (Alg. 4 runs both phases every iteration)."""
    triangular_target_cap: float | None = Field(None, gt=0)
    """Clip the triangular target d_old(s_i, a_i, ag(s_j)) + d_old(s_j, a_j, g) into [0, cap] steps; None: the sum
    as eq. 31b writes it. Each cathetus is a bootstrapped estimate, the first one usually of a pair no episode
    joined, so the sum can feed on its own overestimates; a cap at the episode length plays Floyd-Warshall's
    "infinity" (README, "Bounded triangular targets")."""
    uncertainty_scale: float = Field(400.0, ge=0)
    """C of U = C / (1 + N(s, a))^M (eq. 29, App. E.1.2)."""
    uncertainty_exponent: float = Field(2.0, gt=0)
    """M of U = C / (1 + N(s, a))^M (eq. 29, App. E.1.2)."""
    clip_obs: float = Field(200.0, gt=0)
    """Inputs are clipped to +-clip_obs before normalisation (as the learners' inputs, Table 19)."""
    clip_normalized: float = Field(5.0, gt=0)
    """Normalised inputs are clipped to +-clip_normalized."""

    @model_validator(mode="after")
    def _losses_fit_the_conditioning(self) -> DistanceSettings:
        if self.conditioning == "state" and (self.temporal != "regression" or self.triangular):
            raise ValueError(
                "d(s, g) (conditioning: state) is DDL: it needs temporal: regression and triangular: false; "
                "the off-policy and triangular losses need d(s, a, g)"
            )
        if self.triangular and self.temporal != "off_policy":
            # Eq. 31b's mask reads the pair counts N(s, a, g), which only the off-policy temporal loss keeps.
            raise ValueError("triangular: true needs temporal: off_policy (its mask reads the pair counts)")
        return self


class LearnerSettings(BaseModel):
    """Goal-conditioned SAC or DDPG with HER "future" relabelling (Table 19, section 6.6)."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False, frozen=True, use_attribute_docstrings=True)

    algorithm: Literal["sac", "ddpg"] = "sac"
    """SAC for every task but Fetch Pick&Place, which uses DDPG (section 6.6)."""
    hidden: tuple[int, ...] = Field((256, 256, 256), min_length=1)
    """Hidden widths of the policy and the Q-functions, ReLU, Xavier-uniform weights (Table 19)."""
    learning_rate: float = Field(1e-3, gt=0)
    """Adam learning rate of actor, critics and (SAC) temperature (Table 19)."""
    batch_size: int = Field(256, ge=1)
    """Transitions per update (Table 19)."""
    buffer_size: int = Field(500_000, ge=1)
    """Transitions kept by the learner's replay buffer (Table 19: 5e5)."""
    updates_per_episode: int = Field(100, ge=0)
    """Gradient updates per collected episode (Table 19)."""
    gamma: float = Field(0.98, gt=0, lt=1)
    """Discount factor (Table 19)."""
    polyak: float = Field(0.95, ge=0, lt=1)
    """Target networks move as target <- polyak target + (1 - polyak) online (Table 19)."""
    target_update_interval: int = Field(40, ge=1)
    """Updates between two polyak steps; 40 is OpenAI baselines' batches per cycle, whose defaults Table 19 repeats."""
    her_k: float = Field(4.0, ge=0)
    """HER "future" k: a fraction k / (1 + k) of sampled transitions gets a future achieved goal (Table 19)."""
    random_eps: float = Field(0.3, ge=0, le=1)
    """Probability of a uniformly random exploration action (Table 19, Fig. 27)."""
    action_noise: float = Field(0.2, ge=0)
    """DDPG Gaussian exploration noise, in units of the action range (Table 19)."""
    action_l2: float = Field(1.0, ge=0)
    """DDPG actor penalty on the squared (normalised) action (Table 19)."""
    clip_obs: float = Field(200.0, gt=0)
    """Observations and goals are clipped to +-clip_obs before normalisation (Table 19 = baselines)."""
    clip_normalized: float = Field(5.0, gt=0)
    """Normalised inputs are clipped to +-clip_normalized (baselines)."""
    q_clip_low: float | None = Field(None, lt=0)
    """Lower Q-target clip; None derives it: -1/(1-gamma) for the sparse reward, -T(T+1)/2 for distances (Table 19)."""
    nonnegative_distance: bool = False
    """Reward -max(d, 0) instead of -d. The thesis defaults of the learned rewards switch it on: a distance counts
    steps, and Table 19's Q-target clip at 0 presumes rewards <= 0 (a negative prediction would be a positive
    reward the clip then hides)."""
    reward_scale: float = Field(1.0, gt=0)
    """Multiplies every reward (and the derived Q clip). The thesis defaults use 1 for the sparse reward and 1 / T
    for the learned distances (d / T in [0, ~1], like the sparse reward's scale; README)."""
    init_alpha: float = Field(0.1, gt=0)
    """SAC initial entropy temperature (not in the thesis)."""
    auto_alpha: bool = True
    """Tune the SAC temperature to a target entropy of -|A| (not in the thesis; the usual SAC default)."""


class MethodSettings(BaseModel):
    """Everything one method needs on one task: counts, distance, learner."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False, frozen=True, use_attribute_docstrings=True)

    method: Method
    """Which reward the learner optimises (section 6.6)."""
    counts: CountSettings
    """Hash count models (unused by sparse_her and ddl_her)."""
    distance: DistanceSettings | None
    """Distance network and losses; None for sparse_her."""
    learner: LearnerSettings
    """Policy learner with HER."""


# Table 19 (right): best HER k per task and method. Point Maze's Sparse+HER entry reads "None"; we use
# the HER default 4 there.
HER_K: dict[str, dict[str, float]] = {
    "point_maze": dict(ours_her=0.25, ddl_her=4, offpolicy_ddl_her=4, sparse_her=4),
    "fetch_reach": dict(ours_her=4, ddl_her=4, offpolicy_ddl_her=4, sparse_her=4),
    "fetch_reach_wall": dict(ours_her=4, ddl_her=4, offpolicy_ddl_her=4, sparse_her=4),
    "fetch_pick_place": dict(ours_her=4, ddl_her=4, offpolicy_ddl_her=4, sparse_her=4),
    "fetch_pick_place_wall": dict(ours_her=4, ddl_her=8, offpolicy_ddl_her=8, sparse_her=4),
}

# Table 20 (right) as printed: (k of N(s, a), k of N(s, a, s'), sigma). Plain Fetch Reach shares the
# "FETCH REACH (WITH WALL)" row; FPP with wall shares FPP's.
TABLE_20: dict[str, tuple[int, int, float]] = {
    "point_maze": (64, 32, 20.0),
    "fetch_reach": (128, 128, 0.3),
    "fetch_reach_wall": (128, 128, 0.3),
    "fetch_pick_place": (32, 64, 0.3),
    "fetch_pick_place_wall": (32, 64, 0.3),
}

# App. E.3.1: 50 steps per episode, 100 on Point Maze; the success radii of the environments.
HORIZON: dict[str, int] = {name: 100 if name == "point_maze" else 50 for name in TABLE_20}
SUCCESS_RADIUS: dict[str, float] = {name: 0.45 if name == "point_maze" else 0.05 for name in TABLE_20}

# The defaults: Table 20's key sizes; sigma as printed on Point Maze, where it puts the pair model's
# collision radius (inputs 50 % likely to share their code) at 0.54, about the success radius 0.45.
# On Fetch the printed 0.3 resolves 2 mm (1/25 of the 5 cm success radius) in gymnasium-robotics' units:
# N(s, a, g) counts exact repeats only, the triangular loss never applies (measured: masked fraction 0),
# which contradicts the merge rates of up to 30 % in Fig. 24b. We apply Point Maze's relation instead,
# sigma with the pair model's collision radius at the success radius: 7.4 for k = 128, 3.7 for k = 64
# (README, "Hash granularity"); counts.sigma: 0.3 restores the printed value.
HASH_SIZES: dict[str, tuple[int, int, float]] = {
    "point_maze": (64, 32, 20.0),
    "fetch_reach": (128, 128, 7.4),
    "fetch_reach_wall": (128, 128, 7.4),
    "fetch_pick_place": (32, 64, 3.7),
    "fetch_pick_place_wall": (32, 64, 3.7),
}

# Section 6.6: DDPG + HER on Fetch Pick&Place "due to better empirical performance"; SAC elsewhere.
# We read the wall variant as FPP too.
DDPG_TASKS = frozenset({"fetch_pick_place", "fetch_pick_place_wall"})


def method_settings(method: Method, task_name: str, fetch: bool | None = None) -> MethodSettings:
    """Thesis defaults (Tables 19 and 20) of a method on a task.

    ``task_name`` is one of the keys of :data:`HASH_SIZES`; ``fetch`` (default:
    the name starts with ``fetch``) picks the DDL network size of Table 20
    (2 x 256, 3 x 256 on the Fetch tasks).
    """
    if method not in METHODS:
        raise ValueError(f"unknown method {method!r}; known: {', '.join(METHODS)}")
    if task_name not in HASH_SIZES:
        raise ValueError(f"no thesis settings for task {task_name!r}; known: {', '.join(HASH_SIZES)}")
    fetch = task_name.startswith("fetch") if fetch is None else fetch
    single, pair, sigma = HASH_SIZES[task_name]
    counts = CountSettings(single_key_dim=single, pair_key_dim=pair, sigma=sigma)
    distance: DistanceSettings | None
    if method == "sparse_her":
        distance = None
    elif method == "ddl_her":
        distance = DistanceSettings(
            conditioning="state",
            temporal="regression",
            triangular=False,
            hidden=(256, 256, 256) if fetch else (256, 256),
            buffer_size=100_000,
        )
    elif method == "offpolicy_ddl_her":
        distance = DistanceSettings(triangular=False)
    else:
        distance = DistanceSettings()
    # Learned distances count steps (1 to T): the reward is -max(d, 0) / T, in the sparse reward's range
    # (README, "Reward of the learned distance"); reward_scale 1 and nonnegative_distance false: the literal -d.
    learned = method != "sparse_her"
    learner = LearnerSettings(
        algorithm="ddpg" if task_name in DDPG_TASKS else "sac",
        her_k=HER_K[task_name][method],
        nonnegative_distance=learned,
        reward_scale=1.0 / HORIZON[task_name] if learned else 1.0,
    )
    return MethodSettings(method=method, counts=counts, distance=distance, learner=learner)
