"""Settings of the chapter-5 models and costs, as pydantic models that import no torch.

Sweep files validate these (through the ``mbrl`` method's settings) before
anything runs; keeping them free of torch keeps ``icemlab validate`` fast.
:mod:`~workers.dynamics.ensemble` and :mod:`~workers.dynamics.costs` re-export
them next to the code that uses them.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Annotated, Any, Literal

from pydantic import AfterValidator, BaseModel, ConfigDict, Field, NonNegativeInt, model_validator

if TYPE_CHECKING:
    import torch

MeanPropagation = Literal["none", "per_member", "shared"]
"""PETSUS mean propagation: none (PETS), one mean state per member, or one shared mean state."""

EpistemicTerms = Literal["means_and_variances", "means"]
"""What Var_E of eq. 24 measures over the members: their predicted means' and variances' spread, or the means' only."""

AleatoricStates = Literal["particles", "means"]
"""Where Var_A of eq. 22 is read: at the sampled particle states (as eq. 22 writes it) or at the propagated mean
states (see RazerSettings.aleatoric_states)."""

UncertaintyReduction = Literal["sum_sqrt", "sqrt_sum", "mean_sqrt"]
"""How sqrt(Var) of eq. 26-27 combines the state dimensions (see workers/dynamics/costs.py)."""


def _each_once(dims: tuple[int, ...]) -> tuple[int, ...]:
    if len(set(dims)) < len(dims):
        raise ValueError(f"a dimension is listed twice in {list(dims)}: each counts once")
    return dims


UncertaintyDims = Annotated[tuple[NonNegativeInt, ...], Field(min_length=1), AfterValidator(_each_once)]
"""State dimensions whose uncertainty counts: at least one, none negative, none twice (an empty list would make
the mean over dimensions undefined; use None for all dimensions)."""


class EnsembleConfig(BaseModel):
    """Architecture and training of a probabilistic ensemble; defaults are Table 13 (BridgeMaze)."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False, frozen=True, use_attribute_docstrings=True)

    ensemble_size: int = Field(5, ge=1)
    """Number K of members (ensemble_size, Table 13)."""
    hidden_layers: int = Field(6, ge=1)
    """Hidden layers per member (num_layers, Table 13), each followed by the activation."""
    hidden_size: int = Field(400, ge=1)
    """Units per hidden layer (size, Table 13)."""
    activation: Literal["silu", "relu", "tanh", "elu"] = "silu"
    """Activation of the hidden layers (silu = swish, Table 13); the output layer is linear."""
    min_logvar: float = -10.0
    """Lower soft bound of the predicted log-variance (var_clipping_low, Table 13)."""
    max_logvar: float = 4.0
    """Upper soft bound of the predicted log-variance (var_clipping_high, Table 13)."""
    learn_logvar_bounds: bool = False
    """Train the bounds as parameters with the PETS regulariser 0.01 (sum max - sum min); D.2.1 keeps them fixed."""
    init_std_scale: float = Field(0.5, gt=0)
    """Initial weights: a normal truncated at 2 std with std = init_std_scale / sqrt(fan_in). Table 13 says
    "truncated_normal"; 0.5 is the PETS code's std (and the authors' framework's). Deep nets start with
    almost no signal at 0.5 (6 x 400 SiLU: output std 4e-5), which slows learning what depends on position."""
    lr: float = Field(2e-3, gt=0)
    """Adam learning rate (Table 13)."""
    adam_eps: float = Field(1e-8, gt=0)
    """Adam epsilon (not in the thesis; torch's default)."""
    batch_size: int = Field(512, ge=1)
    """Minibatch size per member (Table 13)."""
    weight_decay: float = Field(1e-5, ge=0)
    """L2 decay of the weight matrices (not biases), applied by Adam (Table 13)."""
    grad_norm: float | None = Field(2.0, gt=0)
    """Clip each member's gradient to this L2 norm, as if it were trained alone; None: no clipping (Table 13/14)."""
    epochs: int = Field(25, ge=1)
    """Passes over all data per training call (Table 13)."""
    bootstrap: bool = False
    """Each member trains on its own sample of the data drawn with replacement, once per training call and
    reshuffled every epoch (PETS' bootstrap), instead of all the data in its own order."""
    input_std_threshold: float = Field(1e-3, ge=0)
    """Input dimensions whose training-data std is below this are centred but not scaled (std taken as 1).
    Not in the thesis: a near-constant input (the quaternion of a cube that rarely tips) would otherwise
    turn a small drift during planning into hundreds of standard deviations and the rollout diverges."""
    state_margin: float | None = Field(0.25, ge=0)
    """Propagated states (particles and means) are clamped to the range of the training data's states, widened
    by this fraction of the range on each side; None: no clamp. Not in the thesis: a model barely trained
    on a few episodes extrapolates linearly far from its data, and 30 compounded steps then grow without
    bound (seen on BridgeMaze: 1e7 after 30 steps, then inf), which leaves every sequence the same cost."""
    keep_function: bool = True
    """When a warm-started ensemble's input normalisation is refitted to the grown dataset, rescale and shift
    every member's first layer so that the members compute the same function of the raw (state, action) as
    before; False: the old weights meet inputs normalised differently from those they were fitted on."""
    retrain_from_scratch: bool = False
    """Re-initialise weights and Adam state at every training call; default warm start (see the module docstring)."""

    @model_validator(mode="after")
    def _bounds_are_ordered(self) -> EnsembleConfig:
        if not self.min_logvar < self.max_logvar:
            raise ValueError(f"min_logvar ({self.min_logvar}) must be below max_logvar ({self.max_logvar})")
        return self

    @classmethod
    def preset(cls, name: str, **overrides: Any) -> EnsembleConfig:
        """A named preset (:data:`ENSEMBLE_PRESETS`) with some fields overridden."""
        try:
            base = ENSEMBLE_PRESETS[name]
        except KeyError:
            raise ValueError(f"unknown ensemble preset {name!r}; known: {', '.join(ENSEMBLE_PRESETS)}") from None
        return cls(**(base | overrides))


ENSEMBLE_PRESETS: dict[str, dict[str, Any]] = {
    # Table 13.
    "bridge_maze": dict(
        ensemble_size=5,
        hidden_layers=6,
        hidden_size=400,
        activation="silu",
        min_logvar=-10.0,
        max_logvar=4.0,
        lr=2e-3,
        batch_size=512,
        weight_decay=1e-5,
        grad_norm=2.0,
        epochs=25,
    ),
    # Table 14 lists only the differences to Table 13: grad_norm None, var_clipping_low -6;
    # ensemble size, activation and var_clipping_high carry over.
    "noisy_halfcheetah": dict(
        ensemble_size=5,
        hidden_layers=4,
        hidden_size=200,
        activation="silu",
        min_logvar=-6.0,
        max_logvar=4.0,
        lr=2e-4,
        batch_size=256,
        weight_decay=3e-5,
        grad_norm=None,
        epochs=50,
    ),
    # Not in the thesis: a net that trains in seconds on a two-core machine (tests, smoke runs).
    "small": dict(
        ensemble_size=5,
        hidden_layers=3,
        hidden_size=64,
        activation="silu",
        min_logvar=-10.0,
        max_logvar=4.0,
        lr=1e-3,
        batch_size=256,
        weight_decay=1e-5,
        grad_norm=2.0,
        epochs=5,
    ),
}


PRESET_SHAPES: dict[str, tuple[int, int]] = {"bridge_maze": (10, 2), "noisy_halfcheetah": (17, 6)}
"""(state dims, action dims) of the task a thesis preset was published for; ``small`` fits any task."""


class SafetyBox(BaseModel):
    """An axis-aligned box violation set C = {s : low_i <= s[dims_i] <= high_i for every i} (App. D.1.3).

    Unconstrained sides are None (e.g. a ceiling: low = height, high = None).
    """

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False, frozen=True, use_attribute_docstrings=True)

    dims: tuple[int, ...] = Field(min_length=1)
    """Observation dimensions the box constrains."""
    low: tuple[float | None, ...]
    """Lower edge per constrained dimension; None: unbounded below."""
    high: tuple[float | None, ...]
    """Upper edge per constrained dimension; None: unbounded above."""

    @model_validator(mode="after")
    def _edges_match_dims(self) -> SafetyBox:
        if not len(self.low) == len(self.high) == len(self.dims):
            raise ValueError(
                f"a safety box needs one low and one high edge per dimension: "
                f"{len(self.dims)} dims, {len(self.low)} low, {len(self.high)} high"
            )
        if len(set(self.dims)) < len(self.dims):
            # Eq. 34's product runs over distinct dimensions; two entries of one would multiply dependent terms.
            raise ValueError(f"a dimension is listed twice in the safety box's dims {list(self.dims)}: give it once, "
                             "with both its edges")  # fmt: skip
        for dim, lo, hi in zip(self.dims, self.low, self.high):
            if dim < 0:
                raise ValueError(f"safety box dimension {dim} is negative")
            if lo is None and hi is None:
                raise ValueError(f"safety box dimension {dim} has neither edge: it would constrain nothing")
            if lo is not None and hi is not None and not lo < hi:
                raise ValueError(f"safety box edge low {lo} is not below high {hi} in dimension {dim}")
        return self

    def edges(self) -> tuple[torch.Tensor, torch.Tensor]:
        """(low, high) float tensors with -inf / inf for unbounded sides."""
        import torch

        low = torch.tensor([-math.inf if v is None else v for v in self.low])
        high = torch.tensor([math.inf if v is None else v for v in self.high])
        return low, high


class RazerSettings(BaseModel):
    """Uncertainty-aware cost settings of RAZER (section 5.3.5, App. D.1.3); all weights zero is PETS."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False, frozen=True, use_attribute_docstrings=True)

    aleatoric_weight: float = Field(0.0, ge=0)
    """w_A of the aleatoric penalty (eq. 26); not published."""
    epistemic_weight: float = Field(0.0, ge=0)
    """w_E of the epistemic bonus (eq. 27); 0.05 for the BridgeMaze exploration run (section 5.4.2)."""
    mean_propagation: MeanPropagation = "per_member"
    """Mean propagation of PETSUS: per_member, shared or none (PETS); see workers/dynamics/propagation.py. The mean
    states feed Var_E alone, so the evaluator propagates them only when epistemic_weight > 0."""
    epistemic_terms: EpistemicTerms = "means_and_variances"
    """Var_E of eq. 24: ``means_and_variances``, the variance over members of their predicted means plus that of
    their predicted variances, as the equation is written; ``means``, the first term alone, the usual
    disagreement measure. The second term is in squared units of the first, and wherever one member's
    log-variance nears its upper bound it outweighs the first many times over (docs/results/razer.md, BridgeMaze)."""
    aleatoric_states: AleatoricStates = "particles"
    """Where Var_A is read: ``particles``, the members' predicted variance at the sampled particle states, as eq. 22
    writes it; ``means``, at the propagated mean states (each member's at its own with per_member mean
    propagation), free of the sampling noise that compounds along the horizon (section 5.4: "RAZER does not rely
    on sampling for the aleatoric part"; App. D.2: "predictions of the covariance Sigma(s_t, a_t)"). ``means``
    needs mean propagation, and the evaluator then propagates the mean states whatever w_E is."""
    uncertainty_reduction: UncertaintyReduction = "sum_sqrt"
    """How sqrt(Var) combines dimensions: sum of per-dim std (default), sqrt of the summed variance, mean std."""
    uncertainty_dims: UncertaintyDims | None = None
    """Observation dimensions whose uncertainty counts; None: all."""
    safety_weight: float = Field(0.0, ge=0)
    """w_S, the penalty per step whose violation probability exceeds delta (eq. 35); 0 disables safety."""
    safety_delta: float = Field(0.05, gt=0, lt=1)
    """delta, the tolerated violation probability per step (eq. 35); not published (Fig. 36b varies it)."""
    safety_boxes: tuple[SafetyBox, ...] = ()
    """Violation sets C; a step counts once if any box's probability exceeds delta."""

    @model_validator(mode="after")
    def _consistent(self) -> RazerSettings:
        if self.epistemic_weight > 0 and self.mean_propagation == "none":
            raise ValueError("epistemic_weight > 0 needs mean propagation (per_member or shared): eq. 24 uses it")
        if self.aleatoric_states == "means" and self.mean_propagation == "none":
            raise ValueError("aleatoric_states: means needs mean propagation (per_member or shared)")
        if self.safety_weight > 0 and not self.safety_boxes:
            raise ValueError("safety_weight > 0 needs at least one safety box")
        return self

    def propagated_means(self) -> MeanPropagation:
        """The mean propagation a rollout needs: the setting where a cost reads the mean states (Var_E of eq. 24
        for w_E > 0, or Var_A with ``aleatoric_states: means``), else none: they would change no cost (the
        particles' random draws do not depend on them) and would add K rows per sequence to every member's batch."""
        if self.epistemic_weight > 0 or self.aleatoric_states == "means":
            return self.mean_propagation
        return "none"

    @classmethod
    def pets(cls) -> RazerSettings:
        """Plain PETS: expected particle cost only, no mean propagation."""
        return cls(mean_propagation="none")
