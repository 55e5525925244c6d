"""Chapter 5 as a method: model-based RL with PETSUS / RAZER, iCEM planning on a learned ensemble.

A trial is a program of rounds (workers/methods/base.py):

* **Round 0** (step 0): the data the loop starts from: ``random_episodes``
  colored-noise episodes in the real environment (and/or a model loaded from
  ``initial_model``), then the first training call.
* **Rounds 1 .. iterations** (step = iteration): one MBRL iteration each:
  plan an episode on the current model in the real environment (iCEM, Alg. 5,
  with RAZER's costs, section 5.3.5) -> add it to the dataset -> the
  ``trainer`` role (an EnsembleTrainer actor) trains on the whole dataset,
  shared once -> new, versioned weights, shared once with the planning workers.
* **The refit** (``frozen.refit_epochs`` > 0, step = iterations + 1): the last
  model trained that many more epochs on the whole dataset before the frozen
  rows (metrics ``refit/...``).
* **Frozen rounds** (``frozen.episodes`` > 0, step = row): the final model
  evaluated without training, one round per row (PETS, then RAZER at each
  ``frozen.aleatoric_weights``, for each of ``frozen.aleatoric_states``), its episodes fanned out to every planning
  worker, all reading one shared weights reference (Fig. 19a: "the same
  model ... trained from data collected during a training run with
  w_E = 0.05"). Every row plays the same episode seeds (common random numbers).

Roles: ``trainer`` (one EnsembleTrainer, stateful: its state is pulled into
every checkpoint and pushed back on restore; a lost trainer costs the round
in flight) and ``planner`` (PlanningWorker, stateless: an episode is a pure
function of weights, settings and seed, so a lost worker is restarted and its
episode retried). As in the ``mpc`` method, the runner plans with a
co-located worker; ``resources.workers.planner: N`` adds N - 1 actors for the
fanned-out episodes (random and frozen ones).

Artifacts: ``models/model_vNNN.npz`` (weights and normaliser, every
``model_every`` iterations and after the last training round) loads with
``DynamicsEnsemble.load("model_v012.npz")`` (``from workers.dynamics import
DynamicsEnsemble``; no pickle involved). Per frozen row, ``frozen/<row>_episodes.csv``: each episode's seed,
ending and metrics, for paired comparisons of rows. For tasks with a plane (BridgeMaze):
``plots/uncertainty_vNNN.png`` beside each model, its one-step Var_A and Var_E
over the plane (workers/dynamics/uncertainty_map.py), and
``plots/visited_states.png``, Fig. 37b/c.

Choices where the thesis is silent, each a setting: see the field docs of
:class:`MbrlSettings`, workers/dynamics/ (ensemble, propagation, costs) and
the task modules.
"""

from __future__ import annotations

import math
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal, Optional

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, create_model, field_validator, model_validator
from pydantic_core import InitErrorDetails, PydanticCustomError

from workers.data import EpisodeBuffer, Trajectory
from workers.dynamics.settings import (
    ENSEMBLE_PRESETS,
    AleatoricStates,
    PRESET_SHAPES,
    EnsembleConfig,
    EpistemicTerms,
    MeanPropagation,
    RazerSettings,
    SafetyBox,
    UncertaintyDims,
    UncertaintyReduction,
)
from workers.methods.base import (
    Artifact,
    MethodSettings,
    Program,
    RoleSpec,
    RoundReport,
    TrialSpec,
    located_error,
)
from workers.planning.config import PRESETS, PlannerConfig

if TYPE_CHECKING:
    from workers.dynamics.uncertainty_map import UncertaintyMap

PresetName = Literal["bridge_maze", "noisy_halfcheetah", "small"]


class _Settings(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False, frozen=True, use_attribute_docstrings=True)


def _optional_fields(model: type[BaseModel], skip: tuple[str, ...] = ()) -> dict[str, Any]:
    """Every field of ``model`` as an optional field (None: the default chosen at resolve time), same docs."""
    from typing import Annotated

    fields = {}
    for name, info in model.model_fields.items():
        if name in skip:
            continue
        annotation = Annotated[(info.annotation, *info.metadata)] if info.metadata else info.annotation
        fields[name] = (Optional[annotation], Field(None, description=info.description))  # noqa: UP045
    return fields


_ModelBase = type("_ModelBase", (_Settings,), {"__doc__": "The ensemble: a preset and per-field overrides."})
ModelSettings = create_model(
    "ModelSettings",
    __base__=_ModelBase,
    __doc__=(
        "The probabilistic ensemble: a preset (Table 13 bridge_maze, Table 14 noisy_halfcheetah, or small for "
        "two-core machines) and per-field overrides; after resolution every field holds the value used."
    ),
    preset=(
        Optional[PresetName],  # noqa: UP045
        Field(None, description="Preset of Tables 13/14 or small; default: the task's (its ensemble_preset)."),
    ),
    **_optional_fields(EnsembleConfig),
)

# Table 15 (BridgeMaze) in PlannerConfig's terms: num_simulated_trajectories 128 per CEM-iteration
# (factor_decrease_num 1: no population decay), opt_iterations 3, horizon 30, elite_size 10, alpha 0.1,
# init_std 0.5, fraction_elites_reused 0.3, keep_previous_elites, shift_elites_over_time,
# execute_best_elite, use_mean_actions (add the mean), colored noise with the task's beta (2.0).
# reevaluate_elites is not in the table: the evaluator is stochastic, so kept elites are evaluated
# again rather than keeping a lucky draw (PlannerConfig.reevaluate_elites).
TABLE_15: dict[str, Any] = dict(
    algorithm="icem",
    budget=None,
    iterations=3,
    population=128,
    population_decay=1.0,
    elites=10,
    horizon=30,
    sigma_init=0.5,
    momentum=0.1,
    elite_fraction=0.3,
    keep_elites=True,
    shift_elites=True,
    shift_mean=True,
    best_action=True,
    add_mean=True,
    bounds="clip",
    reevaluate_elites=True,
)

def planner_defaults(task: Any, given: dict[str, Any]) -> dict[str, Any]:
    """Table 15 with the task's differences (Table 16), less what the sweep's own planner fields decide.

    A budget chooses the schedule (Table 4, or the missing one of iterations and population), so it drops
    the table's iterations and population; another algorithm than iCEM brings its own preset switches
    (section 3.1.1), so it drops Table 15's, which are iCEM's.
    """
    defaults = TABLE_15 | task.planner_defaults
    if given.get("budget") is not None:
        defaults = {k: v for k, v in defaults.items() if k not in ("budget", "iterations", "population")}
    if given.get("algorithm", "icem") != "icem":
        defaults = {k: v for k, v in defaults.items() if k not in PRESETS["icem"]}
    return defaults


_PlannerBase = type("_PlannerBase", (_Settings,), {"__doc__": "iCEM on the learned model."})
MbrlPlannerSettings = create_model(
    "MbrlPlannerSettings",
    __base__=_PlannerBase,
    __doc__=(
        "iCEM on the learned model; unset fields take Table 15 (BridgeMaze) with the task's differences "
        "(Table 16 for Noisy-HalfCheetah: 120 trajectories, 4 iterations, beta 0.25). best_action: true executes "
        "the best elite's first action (Table 15), false the mean's (section 5.3.1); reevaluate_elites "
        "defaults to true (a stochastic evaluator). A budget replaces the table's iterations and population "
        "(Table 4 schedules it); without one, budget records the trajectories spent per step. Another algorithm "
        "takes its own preset switches instead of Table 15's iCEM ones."
    ),
    **_optional_fields(PlannerConfig),
)


class RazerCostSettings(_Settings):
    """RAZER's cost (section 5.3.5, App. D.1.3): all weights zero without mean propagation is PETS."""

    aleatoric_weight: float = Field(0.0, ge=0)
    """w_A, the aleatoric penalty weight (eq. 26); not published."""
    epistemic_weight: float = Field(0.0, ge=0)
    """w_E, the epistemic bonus weight (eq. 27); 0.05 for the BridgeMaze exploration run (section 5.4.2)."""
    mean_propagation: MeanPropagation = "per_member"
    """PETSUS mean propagation: per_member (App. D.2.4), shared (eq. 24's s_bar) or none (PETS); used only where
    epistemic_weight > 0 (the mean states feed Var_E alone)."""
    epistemic_terms: EpistemicTerms = "means_and_variances"
    """Var_E of eq. 24: the members' spread of predicted means plus that of predicted variances, as written, or of
    the ``means`` alone (the variances' spread is in squared units and dominates wherever a member's log-variance
    nears its upper bound; docs/results/razer.md, BridgeMaze)."""
    aleatoric_states: AleatoricStates = "particles"
    """Where Var_A is read: at the sampled particle states, as eq. 22 writes it, or at the propagated ``means``
    (free of the sampling noise that compounds along the horizon; section 5.4 says RAZER "does not rely on sampling
    for the aleatoric part"). ``means`` needs mean propagation, which then runs whatever w_E is."""
    uncertainty_reduction: UncertaintyReduction = "sum_sqrt"
    """How sqrt(Var) of eq. 26-27 combines dimensions: sum of per-dimension std (default), sqrt of the summed
    variance, or mean std."""
    uncertainty_dims: UncertaintyDims | None = None
    """State dimensions whose uncertainty counts; None: all."""
    safety_weight: float = Field(0.0, ge=0)
    """w_S (c_max of eq. 35), the cost per step whose violation probability exceeds delta; 0 disables safety."""
    safety_delta: float = Field(0.05, gt=0, lt=1)
    """delta of eq. 35, the tolerated violation probability per step, in (0, 1); not published for the safety runs
    (Fig. 36b varies it). Table 15's "delta 0.0" is read as another field of the authors' framework: BridgeMaze
    has no violation set, and delta 0 would count every step with any chance of violation."""
    safety_boxes: tuple[SafetyBox, ...] | None = None
    """Violation sets C (App. D.1.3) as boxes over state dimensions; None: the task's own (Noisy-HalfCheetah's
    ceiling; none for BridgeMaze)."""

    @model_validator(mode="after")
    def _consistent(self) -> RazerCostSettings:
        if self.epistemic_weight > 0 and self.mean_propagation == "none":
            raise ValueError("epistemic_weight > 0 needs mean propagation (per_member or shared): eq. 24 uses it")
        if self.aleatoric_states == "means" and self.mean_propagation == "none":
            raise ValueError("aleatoric_states: means reads Var_A at the mean states: it needs mean_propagation "
                             "per_member or shared")  # fmt: skip
        return self

    def settings(self, task_boxes: tuple[SafetyBox, ...]) -> RazerSettings:
        """The evaluator's settings, with the task's boxes where none are given."""
        boxes = task_boxes if self.safety_boxes is None else self.safety_boxes
        return RazerSettings(**(self.model_dump() | {"safety_boxes": boxes}))

    def is_pets(self) -> bool:
        """Plain PETS: no mean propagation and no term of RAZER's cost (eq. 25-27, 35)."""
        weights = (self.aleatoric_weight, self.epistemic_weight, self.safety_weight)
        return self.mean_propagation == "none" and not any(weights)


class FrozenSettings(_Settings):
    """Evaluation of the final model without training (Fig. 19a), after the training iterations."""

    episodes: int = Field(0, ge=0)
    """Episodes per row (>= 25 for Fig. 19a); 0: no frozen evaluation."""
    pets: bool = True
    """Include a PETS row (w_A = w_E = w_S = 0, no mean propagation)."""
    aleatoric_weights: list[float] = []
    """One RAZER row per w_A (the x axis of Fig. 19a); the other cost settings are those of ``razer``."""
    aleatoric_states: list[AleatoricStates] = ["particles"]
    """Where the RAZER rows read Var_A: one set of rows (one per w_A) for each entry, ``particles`` (eq. 22, rows
    ``razer_wA_<w>``) and ``means`` (rows ``razer_wA_<w>_means``); see ``razer.aleatoric_states``."""
    epistemic_weight: float = Field(0.0, ge=0)
    """w_E of the RAZER rows (the model is no longer trained, so exploring buys nothing)."""
    refit_epochs: int = Field(0, ge=0)
    """Before the rows, train the loop's last model this many more epochs on the loop's whole dataset (warm
    start; a training round of its own, logged with ``refit/`` metrics and its model); 0: the rows plan on the
    loop's last model as it is. Section 5.4.2 says the rows use "the same model that was trained from data
    collected during a training run with w_E = 0.05": the run's last model, or a model trained on the run's
    data. Each loop call trains ``model.epochs`` on a growing dataset; the small ensemble's last model still
    overstates the one-step noise of the calm walled bridge (docs/results/razer.md, BridgeMaze)."""
    task_options: dict[str, Any] = {}
    """Task options that differ in the frozen rows from the training iterations' ``task_options``, e.g.
    ``episode_length: 200``: the loop collects shorter episodes (it pays for every step with planning and
    training) while the frozen rows run the task's full length. Checked against the task's options."""

    @field_validator("aleatoric_weights")
    @classmethod
    def _non_negative(cls, weights: list[float]) -> list[float]:
        negative = [w for w in weights if w < 0]
        if negative:
            raise ValueError(f"aleatoric weights must be >= 0, got {negative}")
        if len(set(weights)) != len(weights):
            raise ValueError(f"aleatoric weights repeat: {weights}")
        return weights

    @field_validator("aleatoric_states")
    @classmethod
    def _states_once(cls, states: list[AleatoricStates]) -> list[AleatoricStates]:
        if not states:
            raise ValueError("aleatoric_states needs at least one of particles, means")
        if len(set(states)) != len(states):
            raise ValueError(f"aleatoric_states repeat: {states}")
        return states

    @model_validator(mode="after")
    def _has_rows(self) -> FrozenSettings:
        if self.episodes and not self.pets and not self.aleatoric_weights:
            raise ValueError("frozen.episodes > 0 needs rows: pets: true or some aleatoric_weights")
        return self


class MbrlSettings(MethodSettings):
    """Model-based RL with a learned probabilistic ensemble and iCEM (thesis chapter 5)."""

    model: ModelSettings = ModelSettings()  # type: ignore[valid-type]
    """The ensemble (preset and overrides; retrain_from_scratch switches warm start off)."""
    planner: MbrlPlannerSettings = MbrlPlannerSettings()  # type: ignore[valid-type]
    """iCEM's settings (Tables 15/16 unless set)."""
    razer: RazerCostSettings = RazerCostSettings()
    """The planning cost of the training iterations (all weights 0, the default, plan as PETS: mean states are
    propagated only for w_E > 0)."""
    particles: int = Field(5, ge=1)
    """PETSUS particles per action sequence (TS1); not in the thesis (PETS used 20); 5 = one per member of a
    5-ensemble keeps planning affordable on two cores."""
    iterations: int = Field(10, ge=0)
    """MBRL iterations after round 0: each plans one episode on the current model and trains on it."""
    random_episodes: int = Field(1, ge=0)
    """Colored-noise random episodes collected in round 0, the first training data."""
    random_action_scale: float = Field(1.0, gt=0)
    """Standard deviation of the random episodes' colored noise before clipping to [-1, 1] (its beta is the
    planner's noise_beta)."""
    initial_model: str | None = None
    """An ensemble checkpoint (.npz, e.g. an mbrl run's models/model_vNNN.npz) to start from instead of fresh
    weights; it brings its own architecture (leave ``model`` unset). Read on the runner's node."""
    model_every: int = Field(10, ge=0)
    """Log the model (models/model_vNNN.npz, weights only) every this many iterations and after the last
    training round; 0: only after the last."""
    frozen: FrozenSettings = FrozenSettings()
    """Frozen-model evaluation after training (Fig. 19a)."""

    @model_validator(mode="after")
    def _has_data(self) -> MbrlSettings:
        if self.random_episodes == 0 and self.initial_model is None and (self.iterations or self.frozen.episodes):
            raise ValueError(
                "random_episodes is 0 and there is no initial_model: the first model would have nothing to learn "
                "from; collect random episodes or load a model"
            )
        if self.frozen.refit_epochs and not (self.frozen.episodes and (self.random_episodes or self.iterations)):
            raise ValueError(
                "frozen.refit_epochs trains the last model on the loop's data before the frozen rows: it needs "
                "frozen.episodes and data to train on (random_episodes or iterations)"
            )
        return self


# ------------------------------------------------------------------ helpers
def prefixed(error: ValidationError, prefix: tuple[Any, ...]) -> ValidationError:
    """The same errors, located under ``prefix``."""
    details = [
        InitErrorDetails(
            type=PydanticCustomError(
                "invalid", item["msg"].removeprefix("Value error, ").replace("{", "(").replace("}", ")")
            ),
            loc=(*prefix, *item["loc"]),
            input=item.get("input"),
        )
        for item in error.errors()
    ]
    return ValidationError.from_exception_data("MbrlSettings", details)


def training_rounds(settings: MbrlSettings) -> int:
    """Round 0, the iterations and, with ``frozen.refit_epochs``, the refit: the rounds that train."""
    return 1 + settings.iterations + (1 if settings.frozen.refit_epochs else 0)


def derived_seed(*parts: int) -> int:
    """A seed derived from the trial seed and a purpose (the same parts give the same seed)."""
    return int(np.random.SeedSequence(list(parts)).generate_state(1)[0] % 2**31)


RANDOM, ITERATION, FROZEN, TRAIN = 1, 2, 3, 4
"""Purposes of derived seeds."""


def read_model_meta(path: str) -> dict[str, Any]:
    """The metadata of an ensemble checkpoint (shapes, config), without loading torch."""
    import json
    import zipfile

    if not zipfile.is_zipfile(path):
        raise ValueError("not an .npz archive")
    with np.load(path, allow_pickle=False) as archive:
        if "__meta__" not in archive.files:
            raise ValueError("not an ensemble checkpoint (no __meta__ member)")
        return json.loads(archive["__meta__"].tobytes().decode())


def frozen_task(settings: MbrlSettings, task_name: str):
    """The task the frozen rows run: the trial's, with ``frozen.task_options`` over its options."""
    from workers.tasks import make_task, unknown_option_message

    options = dict(settings.task_options) | settings.frozen.task_options
    try:
        return make_task(task_name, options)
    except ValidationError as error:
        item = error.errors()[0]
        message = item["msg"].removeprefix("Value error, ")
        if item["type"] == "extra_forbidden":
            message = unknown_option_message(task_name, str(item["loc"][-1]))
        raise located_error(("frozen", "task_options", *item["loc"]), message, item.get("input")) from None


MEANS_ROW_SUFFIX = "_means"
"""The name suffix of frozen RAZER rows that read Var_A at the mean states (``razer_wA_<w>_means``)."""


def frozen_rows(settings: MbrlSettings) -> list[tuple[str, RazerCostSettings]]:
    """(name, cost settings) of the frozen-evaluation rows: PETS first, then RAZER by w_A."""
    rows = []
    if settings.frozen.pets:
        pets = settings.razer.model_copy(
            update=dict(aleatoric_weight=0.0, epistemic_weight=0.0, safety_weight=0.0, mean_propagation="none")
        )
        rows.append(("pets", pets))
    for states in settings.frozen.aleatoric_states:
        for weight in settings.frozen.aleatoric_weights:
            update = dict(
                aleatoric_weight=weight, epistemic_weight=settings.frozen.epistemic_weight, aleatoric_states=states
            )
            if settings.razer.mean_propagation == "none":
                update["mean_propagation"] = "per_member"
            suffix = MEANS_ROW_SUFFIX if states == "means" else ""
            rows.append((f"razer_wA_{weight:g}{suffix}", settings.razer.model_copy(update=update)))
    return rows


def best_frozen_success(
    results: dict[str, dict[str, float]], rows: list[tuple[str, RazerCostSettings]]
) -> dict[str, float]:
    """The best RAZER row's success rate per reading of Var_A (``frozen_best_success_rate``, the sweep metric:
    eq. 22's reading where the trial ran it, else the mean states'; ``frozen_best_success_rate_means`` beside it
    when both ran). One maximum over both readings would mix two configurations, and over more rows it reads
    higher by chance alone."""
    reading = {name: cost.aleatoric_states for name, cost in rows}
    best: dict[str, float] = {}
    for name, result in results.items():
        if "success_rate" in result and name in reading and name != "pets":
            states = reading[name]
            best[states] = max(best.get(states, -math.inf), result["success_rate"])
    summary = {}
    if best:
        summary["frozen_best_success_rate"] = best.get("particles", best.get("means"))
    if "means" in best and "particles" in best:
        summary["frozen_best_success_rate_means"] = best["means"]
    return summary


def _task_map(task: Any, title: str) -> tuple[Any, Any]:
    """(figure, axis) with the task's map drawn in its plane: walkable rectangles, then walls and rims."""
    import matplotlib.pyplot as plt

    figure, axis = plt.subplots(figsize=(7, 4.6))
    _draw_task_map(axis, task, title, ground="0.85")
    return figure, axis


def _draw_task_map(axis: Any, task: Any, title: str, ground: str | None, layer: int = 0) -> None:
    """The task's walkable rectangles (filled with ``ground``, or outlined only when None) and walls on ``axis``."""
    from matplotlib.patches import Rectangle

    for (x0, x1), (y0, y1) in getattr(task, "map_rectangles", ()):
        fill = dict(facecolor=ground, edgecolor="0.6") if ground else dict(fill=False, edgecolor="white")
        axis.add_patch(Rectangle((x0, y0), x1 - x0, y1 - y0, zorder=layer, **fill))
    for (x0, x1), (y0, y1) in getattr(task, "map_walls", ()):
        axis.add_patch(Rectangle((x0, y0), x1 - x0, y1 - y0, facecolor="0.35", edgecolor="none", zorder=layer))
    ranges = getattr(task, "coverage_range", None)
    if ranges is not None:
        axis.set_xlim(*ranges[0])
        axis.set_ylim(*ranges[1])
    axis.set_xlabel("x")
    axis.set_ylabel("y")
    axis.set_aspect("equal")
    axis.set_title(title)


def visited_states_png(xy: np.ndarray, when: np.ndarray, title: str, task: Any) -> bytes:
    """Fig. 37b/c: visited states in the task's plane, brighter the later the iteration that reached them first."""
    from workers import plots

    figure, axis = _task_map(task, title)
    # Fig. 37: brightness proportional to the time a cell was first encountered; plot later points last.
    order = np.argsort(when, kind="stable")
    points = axis.scatter(xy[order, 0], xy[order, 1], c=when[order], s=3, cmap="viridis", zorder=1)
    figure.colorbar(points, ax=axis, label="iteration first visited (0: random episodes)")
    figure.tight_layout()
    return plots.to_png(figure)


def uncertainty_map_png(umap: UncertaintyMap, title: str, task: Any) -> bytes:
    """U(Var_A) and U(Var_E) of one step from each point of the task's plane, on log colour scales: where the
    model expects noise (what the aleatoric penalty avoids, eq. 26) and where it lacks data (what the epistemic
    bonus seeks, eq. 27); see workers/dynamics/uncertainty_map.py."""
    import matplotlib.pyplot as plt
    from matplotlib.colors import LogNorm

    from workers import plots

    figure, axes = plt.subplots(1, 2, figsize=(13, 4.6))
    panels = ((umap.aleatoric, "aleatoric U(Var_A), eq. 22"), (umap.epistemic, "epistemic U(Var_E), eq. 24"))
    for axis, (values, label) in zip(axes, panels):
        positive = values[values > 0]
        low = float(positive.min()) if positive.size else 1e-6
        norm = LogNorm(vmin=low, vmax=max(float(values.max()), low * 10))
        mesh = axis.pcolormesh(umap.x, umap.y, values.T, shading="nearest", cmap="magma", norm=norm, zorder=0)
        figure.colorbar(mesh, ax=axis, label="per step")
        _draw_task_map(axis, task, label, ground=None, layer=1)
    figure.suptitle(title)
    figure.tight_layout()
    return plots.to_png(figure)


def model_uncertainty_png(model: Any, task: Any, razer: RazerSettings, title: str) -> bytes | None:
    """:func:`uncertainty_map_png` of ``model`` over the task's plane, titled ``title``, the model's version and
    the probe; None for a task without a plane."""
    from workers.dynamics.uncertainty_map import uncertainty_map

    ranges = getattr(task, "coverage_range", None)
    umap = uncertainty_map(model, task, razer, ranges) if ranges is not None else None
    if umap is None:
        return None
    return uncertainty_map_png(umap, f"{title}, model v{model.weights_version}: {task.plane_probe}", task)


PATH_COLOURS = {"success": "tab:green", "fall": "tab:red", "neither": "tab:gray"}
"""How a frozen row's plot colours an episode's path, by how the episode ended."""


def episode_ending(metrics: dict[str, float]) -> str:
    """"success", "fall" or "neither": how an episode ended, from its task metrics."""
    if metrics.get("success", 0.0) > 0:
        return "success"
    return "fall" if metrics.get("falls", 0.0) > 0 else "neither"


def frozen_outcomes_csv(seeds: list[int], outcomes: list, task: Any) -> bytes:
    """One line per episode of a frozen row: its index, seed, ending and task metrics, and where it ended in
    the task's plane (if it has one). Every row plays the same seeds, so two rows' files pair episode by
    episode (a paired test of success, e.g. McNemar's, instead of one of pooled rates)."""
    keys = sorted({k for o in outcomes for k in o.metrics})
    ends = [task.visited_xy(o.trajectory.observations) for o in outcomes]
    plane = bool(outcomes) and all(end is not None for end in ends)
    lines = [",".join(["episode", "seed", "ending", *keys, *(["final_x", "final_y"] if plane else [])])]
    for index, (seed, outcome) in enumerate(zip(seeds, outcomes, strict=True)):
        values = [repr(float(outcome.metrics[k])) if k in outcome.metrics else "" for k in keys]
        final = [repr(float(v)) for v in ends[index][-1]] if plane else []
        lines.append(",".join([str(index), str(seed), episode_ending(outcome.metrics), *values, *final]))
    return ("\n".join(lines) + "\n").encode()


def frozen_paths_png(paths: list[np.ndarray], endings: list[str], title: str, task: Any) -> bytes:
    """The paths of a frozen row's episodes in the task's plane, coloured by how each ended (where PETS and
    RAZER go, section 5.4.2), with the start marked and the count of each ending in the legend."""
    from workers import plots

    figure, axis = _task_map(task, title)
    for path, ending in zip(paths, endings):
        axis.plot(path[:, 0], path[:, 1], color=PATH_COLOURS[ending], linewidth=1, alpha=0.8, zorder=1)
        axis.plot(path[-1, 0], path[-1, 1], marker="x", color=PATH_COLOURS[ending], zorder=2)
    if paths:
        axis.plot(paths[0][0, 0], paths[0][0, 1], marker="o", color="black", zorder=2)
    for ending, colour in PATH_COLOURS.items():
        axis.plot([], [], color=colour, label=f"{ending}: {endings.count(ending)}")
    axis.legend(loc="upper right", fontsize="small")
    figure.tight_layout()
    return plots.to_png(figure)


# ------------------------------------------------------------------ program
class MbrlProgram(Program):
    """Model-based RL with PETSUS / RAZER: collect, train, repeat; then evaluate the frozen model."""

    name = "mbrl"
    Settings = MbrlSettings
    description = "model-based RL on a learned probabilistic ensemble with PETS / RAZER costs (chapter 5)"
    metrics = {
        "episode_return": "final_return",
        "success": "final_success_rate",
        "coverage": "final_coverage",
        "frozen_success": "frozen_best_success_rate",
    }
    label_paths = {"preset": ("model.preset",)}
    role_names = ("trainer", "planner")
    curves = ("episode_return", "success", "coverage")
    curve_step = "MBRL iteration (0: random episodes)"
    """Training rounds log at step = iteration; coverage against it is Fig. 37a."""

    @classmethod
    def report_plots(cls, files: list[str]) -> list[str]:
        """The visited states (Fig. 37b/c), the frozen rows' paths and the final model's uncertainty map."""
        names = sorted(files)
        maps = [f for f in names if Path(f).name.startswith("uncertainty_v")]
        kept = [f for f in names if Path(f).name == "visited_states.png" or Path(f).name.startswith("frozen_")]
        return kept + maps[-1:]

    settings: MbrlSettings

    # --------------------------------------------------------- declaration
    @classmethod
    def task_problem(cls, task_class: type) -> str | None:
        from workers.tasks import ModelBasedTask

        if not issubclass(task_class, ModelBasedTask):
            return (
                f"method mbrl plans on a learned model of a chapter-5 task (bridge_maze, noisy_halfcheetah); "
                f"{task_class.name} is a ground-truth task of method mpc"
            )
        return None

    @classmethod
    def resolve(cls, settings: MbrlSettings, task: Any) -> MbrlSettings:
        """Concrete model, planner and cost settings for ``task``; refuse what does not fit its state."""
        update: dict[str, Any] = {}
        # The ensemble.
        if settings.initial_model is not None:
            update["model"] = cls._initial_model_settings(settings, task)
        else:
            update["model"] = cls._model_settings(settings, task)
        # The planner: Table 15, the task's differences (Table 16), then what the sweep set.
        given = {k: v for k, v in settings.planner.model_dump().items() if v is not None}
        try:
            planner = PlannerConfig(**(planner_defaults(task, given) | given)).resolved(task.colored_noise_beta)
        except ValidationError as error:
            raise prefixed(error, ("planner",)) from None
        if "budget" not in given:  # the budget field then records the trajectories evaluated per step
            planner = planner.model_copy(update={"budget": planner.trajectories_per_step()})
        update["planner"] = MbrlPlannerSettings(**planner.model_dump())
        # The cost: boxes and dimensions must exist in the task's state.
        update["razer"] = cls._razer_settings(settings.razer, task)
        resolved = settings.model_copy(update=update)
        frozen_task(resolved, task.name)  # options the task does not have are refused here, before anything starts
        return resolved

    @classmethod
    def _model_settings(cls, settings: MbrlSettings, task: Any):
        preset = settings.model.preset or task.ensemble_preset
        shape = PRESET_SHAPES.get(preset)
        if shape is not None and shape != (task.observation_dim, task.action_dim):
            raise located_error(
                ("model", "preset"),
                f"preset {preset!r} is the thesis's model of a {shape[0]}-d state with {shape[1]}-d actions; "
                f"{task.name} has a {task.observation_dim}-d state and {task.action_dim}-d actions. Use preset "
                f"{task.ensemble_preset!r} or 'small' (any field can be overridden)",
                preset,
            )
        # An unset field takes the preset's value; one set to null on purpose (state_margin: null, no clamp) is
        # passed on as None.
        chosen = settings.model.model_fields_set
        overrides = {
            k: v for k, v in settings.model.model_dump().items() if (v is not None or k in chosen) and k != "preset"
        }
        try:
            config = EnsembleConfig(**(ENSEMBLE_PRESETS[preset] | overrides))
        except ValidationError as error:
            raise prefixed(error, ("model",)) from None
        return ModelSettings(preset=preset, **config.model_dump())

    @classmethod
    def _initial_model_settings(cls, settings: MbrlSettings, task: Any):
        path = settings.initial_model
        if settings.model.model_fields_set or any(v is not None for v in settings.model.model_dump().values()):
            raise located_error(("model",), "initial_model brings its own architecture; leave model unset", None)
        if not Path(path).is_file():
            raise located_error(("initial_model",), f"no such file: {path}", path)
        try:
            meta = read_model_meta(path)
            config = EnsembleConfig(**meta["config"])
            shape = (int(meta["obs_dim"]), int(meta["action_dim"]))
        except (OSError, ValueError, KeyError, TypeError) as error:
            raise located_error(("initial_model",), f"not an ensemble checkpoint: {error}", path) from None
        if shape != (task.observation_dim, task.action_dim):
            raise located_error(
                ("initial_model",),
                f"the model in {path} predicts a {shape[0]}-d state from {shape[1]}-d actions; {task.name} has a "
                f"{task.observation_dim}-d state and {task.action_dim}-d actions",
                path,
            )
        return ModelSettings(**config.model_dump())

    @classmethod
    def _razer_settings(cls, razer: RazerCostSettings, task: Any) -> RazerCostSettings:
        dims = task.observation_dim
        for index, box in enumerate(razer.safety_boxes or ()):
            outside = [d for d in box.dims if d >= dims]
            if outside:
                raise located_error(
                    ("razer", "safety_boxes", index, "dims"),
                    f"safety box {index} constrains state dimension {outside[0]}, but {task.name}'s state has "
                    f"{dims} dimensions (0 to {dims - 1})",
                    list(box.dims),
                )
        if razer.uncertainty_dims and max(razer.uncertainty_dims) >= dims:
            raise located_error(
                ("razer", "uncertainty_dims"),
                f"dimension {max(razer.uncertainty_dims)} is outside {task.name}'s {dims}-d state",
                list(razer.uncertainty_dims),
            )
        boxes = task.safety_boxes if razer.safety_boxes is None else razer.safety_boxes
        if razer.safety_weight > 0 and not boxes:
            raise located_error(
                ("razer", "safety_weight"),
                f"safety_weight > 0 needs a safety box, and {task.name} has none of its own: set razer.safety_boxes",
                razer.safety_weight,
            )
        return razer.model_copy(update={"safety_boxes": tuple(boxes)})

    @classmethod
    def trains(cls, settings: MbrlSettings) -> bool:
        """Whether the trial trains at all (else it only evaluates an initial model; a refit needs data, so
        it implies one of these)."""
        return settings.random_episodes > 0 or settings.iterations > 0

    @classmethod
    def roles_for(cls, trial: TrialSpec, unit_cpus: int, counts) -> list[RoleSpec]:
        from workers.dynamics.episodes import PlanningWorker
        from workers.dynamics.trainer import EnsembleTrainer
        from workers.tasks import TASKS

        settings: MbrlSettings = trial.settings
        task = TASKS[trial.task]
        roles = []
        if cls.trains(settings):
            config = {k: v for k, v in settings.model.model_dump().items() if k != "preset"}
            kwargs = dict(
                obs_dim=task.observation_dim, action_dim=task.action_dim, config=config, seed=trial.seed, cpus=unit_cpus
            )
            # The trainer and the runner take turns (a round plans, then trains): they share one unit of CPUs,
            # half each in Ray's accounting; the trainer trains with the unit's threads while the runner waits.
            roles.append(RoleSpec("trainer", EnsembleTrainer, 1, unit_cpus / 2, kwargs, stateful=True))
        # The runner plans with a co-located worker; further planning workers are the role's actors.
        remote = max(0, counts.get("planner", 1) - 1)
        if remote:
            roles.append(RoleSpec("planner", PlanningWorker, remote, unit_cpus, cls._planner_kwargs(trial, unit_cpus)))
        return roles

    @classmethod
    def runner_cpus(cls, trial: TrialSpec, unit_cpus: int) -> float:
        """Half a unit when there is a trainer to take turns with (see roles_for), else a whole one."""
        return unit_cpus / 2 if cls.trains(trial.settings) else unit_cpus

    @classmethod
    def _planner_kwargs(cls, trial: TrialSpec, cpus: float) -> dict[str, Any]:
        settings: MbrlSettings = trial.settings
        planner = settings.planner.model_dump()
        return dict(
            task_name=trial.task,
            task_options=settings.task_options,
            planner=planner,
            particles=settings.particles,
            random_beta=float(planner["noise_beta"]),
            random_scale=settings.random_action_scale,
            cpus=cpus,
        )

    @classmethod
    def labels(cls, trial: TrialSpec) -> dict[str, str]:
        settings: MbrlSettings = trial.settings
        razer = settings.razer
        cost = "pets" if razer.is_pets() else f"razer_wA{razer.aleatoric_weight:g}_wE{razer.epistemic_weight:g}"
        if razer.aleatoric_states == "means" and razer.aleatoric_weight:
            cost += "_Ameans"
        if razer.safety_weight:  # the safety term's runs are not the plain w_A / w_E configuration's
            cost += f"_wS{razer.safety_weight:g}_delta{razer.safety_delta:g}"
        return {"preset": str(settings.model.preset or "file"), "cost": cost}

    @classmethod
    def planned_rounds(cls, trial: TrialSpec) -> int:
        settings: MbrlSettings = trial.settings
        rows = len(frozen_rows(settings)) if settings.frozen.episodes else 0
        return training_rounds(settings) + rows

    @classmethod
    def round_work(cls, trial: TrialSpec, counts) -> list[float]:
        """In planned episodes one after another: round 0 plans none (random episodes and a first training), an
        iteration plans one, a frozen row its episodes spread over the planning workers (see _run_episodes),
        each as long as the frozen task's episodes are against the loop's (``frozen.task_options``)."""
        from workers.tasks import make_task

        settings: MbrlSettings = trial.settings
        workers = max(1, counts.get("planner", 1))
        length = 1.0
        if settings.frozen.task_options:
            loop = make_task(trial.task, settings.task_options).episode_length
            length = frozen_task(settings, trial.task).episode_length / loop
        row = float(math.ceil(settings.frozen.episodes / workers)) * length
        rows = len(frozen_rows(settings)) if settings.frozen.episodes else 0
        refit = [0.0] if settings.frozen.refit_epochs else []  # trains only, as round 0 does
        return [0.0] + [1.0] * settings.iterations + refit + [row] * rows

    # ----------------------------------------------------------------- run
    def __init__(self, trial: TrialSpec, roles, cpus: int):
        super().__init__(trial, roles, cpus)
        from workers.dynamics.episodes import PlanningWorker
        from workers.tasks import make_task

        self.settings = trial.settings
        self.task = make_task(trial.task, self.settings.task_options)
        # The co-located worker plans with the runner's CPUs (at least one thread).
        self.local = PlanningWorker(**self._planner_kwargs(trial, max(1, int(cpus))))
        self.trainer = roles.get("trainer")
        self.remote = roles.get("planner")
        self.buffer = EpisodeBuffer()
        self.episode_rounds: list[int] = []
        """The round (iteration) each episode of the buffer was collected in."""
        self.weights = None
        self.history: dict[str, list[float]] = {"return": [], "success": []}
        self.frozen_results: dict[str, dict[str, float]] = {}
        self.rows = frozen_rows(self.settings) if self.settings.frozen.episodes else []
        self.frozen_task = frozen_task(self.settings, trial.task) if self.settings.frozen.task_options else self.task
        self.training_rounds = training_rounds(self.settings)

    # ----------------------------------------------------- episodes
    def _run_episodes(self, weights, jobs: list, label: str) -> list:
        """Run ``jobs`` on the co-located worker and the planner actors, all reading one weights reference."""
        workers = 1 + (self.remote.size if self.remote is not None else 0)
        fans_out = workers > 1 and len(jobs) > 1
        shared = self.remote.share(weights) if (fans_out and weights is not None) else weights
        pending = {}
        for index, job in enumerate(jobs):
            member = index % workers
            if member:
                pending[index] = self.remote.submit(member - 1, "run_episode", shared, job)
        results: dict[int, Any] = {}

        def episodes_done() -> None:
            # The planner actors' episodes count as they finish, not when the local share is done: otherwise a
            # frozen row reads "9/25" (the local share) until its last episode returns.
            finished = len(results) + sum(call.done() for index, call in pending.items() if index not in results)
            self.set_progress(finished / len(jobs), f"{label}: {finished}/{len(jobs)} episodes")

        local_jobs = [i for i in range(len(jobs)) if i % workers == 0]
        for count, index in enumerate(local_jobs):

            def on_step(step: int, steps: int, count: int = count) -> None:
                done = (count + step / steps) / max(len(local_jobs), 1)
                self.set_progress(done, f"{label}: step {step}/{steps}")

            results[index] = self.local.run_episode(weights, jobs[index], on_step if len(jobs) == 1 else None)
            episodes_done()
        for index, call in pending.items():
            results[index] = call.result()
            episodes_done()
        return [results[i] for i in range(len(jobs))]

    # ----------------------------------------------------- training
    def _dataset(self):
        from workers.dynamics.ensemble import Transitions

        transitions = self.buffer.transitions()
        return Transitions(transitions.observations, transitions.actions, transitions.next_observations)

    def _train(self, index: int, newest: int, epochs: int | None = None, label: str | None = None) -> dict[str, float]:
        """Train on the whole dataset (shared once); rows from ``newest`` on are held out first; ``epochs``
        overrides the model's epochs for this call."""
        self.set_progress(0.9, label or f"round {index}: training on {self.buffer.steps} transitions")
        dataset = self.trainer.share(self._dataset())
        seed = derived_seed(self.trial.seed, TRAIN, index)
        started = time.perf_counter()
        report = self.trainer.submit(0, "train", dataset, newest, seed, epochs).result()
        self.weights = report.weights
        return report.metrics | {"train_call_seconds": time.perf_counter() - started}

    # ----------------------------------------------------- rounds
    def run_round(self, index: int) -> RoundReport:
        started = time.perf_counter()
        if index == 0:
            metrics, artifacts = self._round_zero()
        elif index <= self.settings.iterations:
            metrics, artifacts = self._iteration(index)
        elif index < self.training_rounds:
            metrics, artifacts = self._refit(index)
        else:
            metrics, artifacts = self._frozen_round(index - self.training_rounds)
        seconds = time.perf_counter() - started
        metrics["round_seconds" if index < self.training_rounds else "frozen/round_seconds"] = seconds
        done = index + 1 >= self.total_rounds()
        step = index if index < self.training_rounds else index - self.training_rounds
        return RoundReport(
            index=index,
            metrics=metrics,
            step=step,
            artifacts=artifacts,
            done=done,
            summary=self._summary() if done else {},
        )

    def _round_zero(self) -> tuple[dict[str, float], list[Artifact]]:
        settings = self.settings
        metrics: dict[str, float] = {}
        if settings.initial_model is not None:
            from workers.dynamics.ensemble import read_npz
            from workers.dynamics.trainer import Weights

            arrays, meta = read_npz(settings.initial_model)
            loaded = Weights(int(meta.get("weights_version", 0)), arrays, meta)
            self.weights = loaded if self.trainer is None else self.trainer.submit(0, "load_weights", loaded).result()
            metrics["initial_model_version"] = float(self.weights.version)
        if settings.random_episodes:
            jobs = [
                self._job(derived_seed(self.trial.seed, RANDOM, j), None, "random")
                for j in range(settings.random_episodes)
            ]
            outcomes = self._run_episodes(None, jobs, "round 0: random episodes")
            for outcome in outcomes:
                self._add(outcome.trajectory, 0)
            metrics |= self._episode_metrics(outcomes)
        if self.trainer is not None and self.buffer.steps:
            # A loaded model is scored on the random episodes before it trains on them (held out, as an
            # iteration's newest episode is); a fresh one has learned nothing to score.
            metrics |= self._train(0, 0 if settings.initial_model is not None else self.buffer.steps)
        metrics |= self._data_metrics()
        return metrics, self._model_artifacts(0)

    def _iteration(self, index: int) -> tuple[dict[str, float], list[Artifact]]:
        razer = self.settings.razer.settings(self.task.safety_boxes)
        job = self._job(derived_seed(self.trial.seed, ITERATION, index), razer, f"iteration {index}")
        (outcome,) = self._run_episodes(self.weights, [job], f"iteration {index}/{self.settings.iterations}")
        newest = self.buffer.steps
        self._add(outcome.trajectory, index)
        metrics = self._episode_metrics([outcome])
        self.history["return"].append(metrics["episode_return"])
        self.history["success"].append(metrics.get("success", math.nan))
        metrics |= self._train(index, newest)
        metrics |= self._data_metrics()
        return metrics, self._model_artifacts(index)

    def _refit(self, index: int) -> tuple[dict[str, float], list[Artifact]]:
        """``frozen.refit_epochs`` more epochs for the last model on the whole dataset, before the frozen rows."""
        epochs = self.settings.frozen.refit_epochs
        metrics = self._train(index, self.buffer.steps, epochs, f"refitting the last model for {epochs} epochs")
        return {f"refit/{k}": v for k, v in metrics.items()}, self._model_artifacts(index)

    def _frozen_round(self, row: int) -> tuple[dict[str, float], list[Artifact]]:
        name, cost = self.rows[row]
        razer = cost.settings(self.frozen_task.safety_boxes)
        episodes = self.settings.frozen.episodes
        options = self.settings.frozen.task_options or None
        jobs = [self._job(derived_seed(self.trial.seed, FROZEN, e), razer, name, options) for e in range(episodes)]
        outcomes = self._run_episodes(self.weights, jobs, f"frozen {name}")
        episode = self._episode_metrics(outcomes)
        result = {
            "mean_return": episode["episode_return"],
            "aleatoric_weight": cost.aleatoric_weight,
            "pets": float(cost.is_pets()),
            "episodes": float(episodes),
            "mean_steps": episode["steps"],
        }
        for key in ("success", "falls", "safety_violations", "box_drops", "planning_seconds_per_step"):
            if key in episode:
                result[key if key in ("safety_violations", "planning_seconds_per_step") else f"{key}_rate"] = episode[
                    key
                ]
        result |= {k: v for k, v in episode.items() if k.startswith("cost/")}
        self.frozen_results[name] = result
        metrics = {f"frozen/{k}": v for k, v in result.items()}
        seeds = [job.seed for job in jobs]
        outcomes_csv = Artifact(f"frozen/{name}_episodes.csv", frozen_outcomes_csv(seeds, outcomes, self.frozen_task))
        return metrics, [outcomes_csv, *self._frozen_paths(name, outcomes)]

    # ----------------------------------------------------- records
    def _job(self, seed: int, razer, label: str, task_options: dict[str, Any] | None = None):
        from workers.dynamics.episodes import EpisodeJob

        return EpisodeJob(seed, None if razer is None else razer.model_dump(), label, task_options)

    def _add(self, trajectory: Trajectory, round_index: int) -> None:
        self.buffer.add(Trajectory(trajectory.observations, trajectory.actions, trajectory.rewards))
        self.episode_rounds.append(round_index)

    @staticmethod
    def _episode_metrics(outcomes: list) -> dict[str, float]:
        """Means over the episodes of every metric they report, ``return`` as ``episode_return``."""
        keys = sorted({k for o in outcomes for k in o.metrics})
        means = {}
        for key in keys:
            values = [o.metrics[key] for o in outcomes if key in o.metrics]
            means["episode_return" if key == "return" else key] = float(np.mean(values))
        if "coverage" in means:
            means["episode_coverage"] = means.pop("coverage")
        versions = [o.weights_version for o in outcomes if o.weights_version is not None]
        if versions:
            means["planned_with_version"] = float(versions[0])
        return means

    def _data_metrics(self) -> dict[str, float]:
        metrics = {"dataset_size": float(self.buffer.steps), "dataset_episodes": float(len(self.buffer))}
        if self.weights is not None:
            metrics["weights_version"] = float(self.weights.version)
        grid = self._coverage_grid()
        if grid is not None:
            metrics["coverage"] = float(np.mean(grid))
        return metrics

    def _coverage_grid(self):
        grid = None
        for trajectory in self.buffer.episodes:
            cells = self.task.coverage_grid(trajectory.observations)
            if cells is None:
                return None
            grid = cells if grid is None else grid | cells
        return grid

    def _model_artifacts(self, index: int) -> list[Artifact]:
        from workers.dynamics.ensemble import npz_bytes

        if self.weights is None or self.trainer is None:
            return []
        last = index + 1 == self.training_rounds
        loop_end = index == self.settings.iterations  # the loop's last model, also when a refit follows
        every = self.settings.model_every
        if not (last or loop_end or (every and index % every == 0 and index > 0)):
            return []
        artifacts = [
            Artifact(f"models/model_v{self.weights.version:03d}.npz", npz_bytes(self.weights.arrays, self.weights.meta))
        ]
        figure = self._uncertainty_map_png()
        if figure is not None:
            artifacts.append(Artifact(f"plots/uncertainty_v{self.weights.version:03d}.png", figure))
        if loop_end:
            figure = self._visited_states_png()
            if figure is not None:
                artifacts.append(Artifact("plots/visited_states.png", figure))
        return artifacts

    def _uncertainty_map_png(self) -> bytes | None:
        """The current model's one-step Var_A and Var_E over the task's plane (tasks with one, e.g. BridgeMaze)."""
        from workers.dynamics.ensemble import DynamicsEnsemble

        model = DynamicsEnsemble.from_state(self.weights.arrays, self.weights.meta)
        razer = self.settings.razer.settings(self.task.safety_boxes)
        return model_uncertainty_png(model, self.task, razer, f"{self.trial.task} s{self.trial.seed}")

    def _frozen_paths(self, name: str, outcomes: list) -> list[Artifact]:
        """plots/frozen_<row>.png: where the row's episodes went (tasks with a plane to draw in)."""
        task = self.frozen_task
        paths = [task.visited_xy(outcome.trajectory.observations) for outcome in outcomes]
        if not paths or any(path is None for path in paths):
            return []
        endings = [episode_ending(outcome.metrics) for outcome in outcomes]
        title = f"{self.trial.task} frozen {name} s{self.trial.seed}: {len(paths)} episodes"
        return [Artifact(f"plots/frozen_{name}.png", frozen_paths_png(paths, endings, title, task))]

    def _visited_states_png(self) -> bytes | None:
        """Fig. 37b/c: every visited state in the plane of the task, brighter the later it was first reached."""
        points, when = [], []
        for trajectory, round_index in zip(self.buffer.episodes, self.episode_rounds):
            xy = self.task.visited_xy(trajectory.observations)
            if xy is None:
                return None
            points.append(xy)
            when.append(np.full(len(xy), round_index))
        if not points:
            return None
        return visited_states_png(
            np.concatenate(points),
            np.concatenate(when),
            f"{self.trial.task} {self.labels(self.trial)['cost']} s{self.trial.seed}: visited states",
            self.task,
        )

    def _summary(self) -> dict[str, float]:
        # Summary keys differ from the rounds' metric keys: both are logged to one run (the summary at step 0).
        summary: dict[str, float] = {"final_dataset_size": float(self.buffer.steps)}
        returns = self.history["return"]
        if returns:
            window = slice(-min(5, len(returns)), None)
            summary["final_return"] = float(np.mean(returns[window]))
            summary["mean_return"] = float(np.mean(returns))
            successes = [s for s in self.history["success"][window] if not math.isnan(s)]
            if successes:
                summary["final_success_rate"] = float(np.mean(successes))
                summary["final_success_rate_episodes"] = float(len(successes))  # one episode per iteration
        grid = self._coverage_grid()
        if grid is not None:
            summary["final_coverage"] = float(np.mean(grid))
        for name, result in self.frozen_results.items():
            for key, value in result.items():
                if not key.startswith("cost/"):
                    summary[f"frozen/{name}/{key}"] = value
        return summary | best_frozen_success(self.frozen_results, self.rows)

    # ----------------------------------------------------------- state
    def state_dict(self) -> dict[str, Any]:
        state: dict[str, Any] = {
            "buffer": self.buffer.to_tree(),
            "episode_rounds": np.array(self.episode_rounds, dtype=np.int64),
            "history": {k: np.array(v, dtype=np.float64) for k, v in self.history.items()},
            # Result keys hold '/' (cost/c), which checkpoint paths reserve: rows go in as JSON pairs.
            "frozen": [[name, [[k, v] for k, v in result.items()]] for name, result in self.frozen_results.items()],
        }
        if self.trainer is not None:
            state["trainer"] = self.trainer.submit(0, "state_dict").result()
        elif self.weights is not None:
            state["weights"] = {
                "version": self.weights.version,
                "arrays": self.weights.arrays,
                "meta": self.weights.meta,
            }
        return state

    def load_state_dict(self, state: dict[str, Any]) -> None:
        from workers.dynamics.trainer import Weights

        self.buffer = EpisodeBuffer.from_tree(state["buffer"])
        self.episode_rounds = [int(r) for r in np.asarray(state["episode_rounds"])]
        self.history = {k: [float(x) for x in np.asarray(v)] for k, v in state["history"].items()}
        self.frozen_results = {name: {k: float(v) for k, v in pairs} for name, pairs in state.get("frozen") or []}
        if "trainer" in state:
            self.trainer.submit(0, "load_state_dict", state["trainer"]).result()
            self.weights = self.trainer.submit(0, "weights").result()
        elif "weights" in state:
            stored = state["weights"]
            self.weights = Weights(
                int(stored["version"]), {k: np.asarray(v) for k, v in stored["arrays"].items()}, stored["meta"]
            )

    def close(self) -> None:
        self.local.close()
