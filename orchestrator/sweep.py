"""Sweep files: schema, YAML loading with located errors, expansion into trials.

A sweep YAML names a task and a method (``mpc`` by default: chapter 3's MPC
episodes; the other chapters' methods as they are registered in
workers/methods), the method's base settings, the parameters to vary (grid
``values`` or random ``distribution`` draws over dotted paths such as
``planner.budget``, derived from the method's settings model), named variants
and the seeds. Loading validates the file and every concrete trial it expands
to before anything runs; problems come back as :class:`SweepError` with one
``FILE:LINE: path: message`` per problem.
"""

from __future__ import annotations

import copy
import hashlib
import itertools
import json
import math
import typing
from pathlib import Path
from typing import Annotated, Any, Literal, NamedTuple

import numpy as np
import yaml
from pydantic import (
    AfterValidator,
    BaseModel,
    ConfigDict,
    Field,
    SerializeAsAny,
    ValidationError,
    ValidationInfo,
    field_validator,
    model_validator,
)

from orchestrator.references import THESIS, Reference, load_references
from orchestrator.yaml_problems import (  # noqa: F401 (SweepError and SweepProblem are re-exported)
    SweepError,
    SweepProblem,
    booleans_for_numbers,
    closest_hint,
    node_line,
    problems_from,
    read_yaml,
    sorted_problems,
    submodel,
)
from workers import MAX_SEED
from workers.methods import BUILTIN_METHODS, DEFAULT_METHOD, METHODS, MethodSettings, Program, TrialSpec
from workers.planning.config import Algorithm
from workers.tasks import TASKS, make_task, unknown_option_message, unknown_task_message

DEFAULT_MAX_TRIALS = 1000
MethodName = Literal[tuple(METHODS)]  # type: ignore[valid-type]


class _UserModel(BaseModel):
    """Base of everything a user writes: unknown keys are errors."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False, use_attribute_docstrings=True)


class GridParameter(_UserModel):
    """A parameter taking each of a list of values (grid search)."""

    values: list[Any] = Field(min_length=1)
    """The values to try; the sweep runs every combination of grid parameters."""


class RandomParameter(_UserModel):
    """A parameter drawn at random, ``num_samples`` times per sweep."""

    distribution: Literal["uniform", "loguniform", "randint", "choice"]
    """uniform / loguniform on [low, high], randint on {low, ..., high}, or choice among ``choices``."""
    low: float | None = None
    """Lower end of the range (uniform, loguniform, randint)."""
    high: float | None = None
    """Upper end of the range (uniform, loguniform, randint)."""
    choices: list[Any] | None = None
    """The options of a ``choice`` distribution."""

    @model_validator(mode="after")
    def _check_range(self) -> RandomParameter:
        if self.distribution == "choice":
            if not self.choices:
                raise ValueError("a choice distribution needs a non-empty 'choices' list")
        else:
            if self.low is None or self.high is None:
                raise ValueError(f"a {self.distribution} distribution needs 'low' and 'high'")
            if not (math.isfinite(self.low) and math.isfinite(self.high) and math.isfinite(self.high - self.low)):
                raise ValueError(f"low and high must be finite and a finite distance apart: {self.low}, {self.high}")
            if self.low > self.high:
                raise ValueError(f"low ({self.low}) is above high ({self.high})")
            if self.distribution == "randint":
                if not (float(self.low).is_integer() and float(self.high).is_integer()):
                    raise ValueError(f"a randint distribution needs whole-number bounds, got {self.low}, {self.high}")
                if max(abs(self.low), abs(self.high)) > 2**62:
                    raise ValueError(f"randint bounds must be within +-2**62, got {self.low}, {self.high}")
            if self.distribution == "loguniform" and self.low <= 0:
                raise ValueError("a loguniform distribution needs low > 0")
        return self

    def draw(self, rng: np.random.Generator) -> Any:
        if self.distribution == "choice":
            return self.choices[int(rng.integers(len(self.choices)))]
        if self.distribution == "randint":
            return int(rng.integers(int(self.low), int(self.high) + 1))
        if self.distribution == "loguniform":
            return float(math.exp(rng.uniform(math.log(self.low), math.log(self.high))))
        return float(rng.uniform(self.low, self.high))


class SeedRange(_UserModel):
    """Consecutive seeds: ``first``, ``first + 1``, ..., ``count`` of them."""

    first: int = Field(0, ge=0)
    """The first seed."""
    count: int = Field(ge=1)
    """How many seeds."""

    @model_validator(mode="after")
    def _last_seed_fits(self) -> SeedRange:
        if self.first + self.count - 1 > MAX_SEED:
            raise ValueError(f"the last seed, {self.first + self.count - 1}, is above the largest, {MAX_SEED}")
        return self


class Resources(_UserModel):
    """How a trial uses the machine or cluster (does not change results)."""

    simulation_workers: int = Field(1, ge=1)
    """Simulation workers per trial (one co-located with the trial, the others separate actors); a planning
    batch is split between them."""
    threads_per_worker: int | None = Field(None, ge=1)
    """CPUs (native rollout or torch threads) per worker. Default: the cluster's CPUs shared by the trials
    that run at once."""
    workers: dict[str, int] = {}
    """Workers per role of the method, e.g. {relabel: 2} (see each method's roles)."""

    @field_validator("workers")
    @classmethod
    def _positive_counts(cls, workers: dict[str, int]) -> dict[str, int]:
        bad = {k: v for k, v in workers.items() if v < 1}
        if bad:
            raise ValueError(f"worker counts must be >= 1, got {bad}")
        return workers


class Metric(_UserModel):
    """The figure a sweep is summarised and compared by."""

    name: str | None = None
    """A headline figure of the method (mpc: episode_return or success); default the method's first."""
    mode: Literal["max", "min"] = "max"
    """Whether higher is better: reports mark the best configuration by it."""


class Tracking(_UserModel):
    """Where results go in MLflow."""

    experiment: str | None = None
    """MLflow experiment; default: the sweep name."""
    tags: dict[str, str] = {}
    """Extra tags on the sweep's parent run."""


def _named_variant(variant: dict[str, Any]) -> dict[str, Any]:
    name = variant.get("name")
    if not isinstance(name, str) or not name:
        raise ValueError("a variant needs a 'name', e.g. - {name: no-colored-noise, planner.noise_beta: 0}")
    return variant


class Sweep(_UserModel):
    """A sweep file: what to run, over which parameters and seeds, and how."""

    name: str = Field(pattern=r"^[A-Za-z0-9][A-Za-z0-9_.\-]*$", max_length=100)
    """Sweep name (letters, digits, _ . -); names the MLflow experiment by default."""
    task: str
    """Task name, e.g. halfcheetah_running (see `icemlab tasks`)."""
    method: MethodName = DEFAULT_METHOD
    """The method every trial runs (see `icemlab schema`): mpc (chapter 3) or a learning method."""
    algorithm: Algorithm | None = None
    """method mpc: the planner of the CEM family (icem, cem, cem_mpc, cem_pets); default icem."""
    base: dict[str, Any] = {}
    """The method's settings shared by all trials (for mpc: planner, episodes, max_steps, task_options, ...)."""
    parameters: dict[str, GridParameter | RandomParameter] = {}
    """Parameters to vary, by dotted path into the method's settings (e.g. planner.budget) or task / algorithm."""
    variants: list[Annotated[dict[str, Any], AfterValidator(_named_variant)]] = []
    """Named sets of overrides run side by side, e.g. ablations (thesis Fig. 7):
    [{name: full}, {name: no-colored-noise, planner.noise_beta: 0}]. Combined with every grid point and seed."""
    num_samples: int = Field(1, ge=1)
    """Draws of the random parameters (each combined with every grid point and seed)."""
    seeds: Annotated[list[int], Field(min_length=1)] | SeedRange = [0]
    """Seeds, as a list or as {first, count}; every configuration runs once per seed."""
    metric: Metric = Metric()
    """The figure summarising each configuration in reports."""
    baseline: list[str] = []
    """Variants the others are compared with in reports (a name or a list): each configuration meets the first
    listed baseline of its own task, labels (algorithm, budget) and grid point on the seeds both ran, e.g.
    [icem, cem_mpc] for ablations of both; episode by episode where the method's episodes start alike in every
    configuration (mpc: episode i of a seed starts from the same state). Success flags get McNemar's exact test,
    returns the paired t-test."""
    resources: Resources = Resources()
    """CPU and worker layout of each trial."""
    retries: int = Field(1, ge=0, le=10)
    """How often a trial whose code raised is tried again (from its last checkpoint) before it is FAILED;
    an error that repeats identically is not retried again."""
    max_lost_processes: int = Field(20, ge=0)
    """How many lost processes (killed actors or nodes, memory kills, preemption) a trial recovers from before it
    is FAILED: a stateless worker by Ray's restart and retried call, a stateful one from the last completed round,
    the trial's runner from its last checkpoint. Each process counts: a lost node spends one for the runner (if it
    was there) and one per worker of the trial it held."""
    max_trials: int = Field(DEFAULT_MAX_TRIALS, ge=1)
    """Refuse sweeps that expand to more trials than this (guards against runaway grids)."""
    tracking: Tracking = Tracking()
    """MLflow experiment and tags."""
    reference: str | None = None
    """Published figures to compare with: a YAML file, relative to the sweep file (default: the thesis's)."""

    @field_validator("task")
    @classmethod
    def _known_task(cls, task: str) -> str:
        if task not in TASKS:
            raise ValueError(unknown_task_message(task))
        return task

    @field_validator("seeds", mode="before")
    @classmethod
    def _seeds_are_a_list_or_a_range(cls, seeds: Any) -> Any:
        if not isinstance(seeds, (list, dict, SeedRange)):
            raise ValueError(f"seeds are a list, e.g. [0, 1, 2], or a range, e.g. {{first: 0, count: 5}}: {seeds!r}")
        return seeds

    @field_validator("seeds")
    @classmethod
    def _non_negative_seeds(cls, seeds: list[int] | SeedRange) -> list[int] | SeedRange:
        if isinstance(seeds, SeedRange):
            return seeds
        negative = [s for s in seeds if s < 0]
        if negative:
            raise ValueError(f"seeds must be >= 0, got {negative[:5]}")
        too_large = [s for s in seeds if s > MAX_SEED]
        if too_large:
            raise ValueError(f"seeds must be at most {MAX_SEED}, got {too_large[:5]}")
        if len(set(seeds)) != len(seeds):
            raise ValueError("seeds must not repeat (a repeated seed would run the same trial twice)")
        return seeds

    @field_validator("variants")
    @classmethod
    def _variants_are_named_and_distinct(cls, variants: list[dict[str, Any]]) -> list[dict[str, Any]]:
        names = [variant["name"] for variant in variants]
        if len(set(names)) != len(names):
            raise ValueError(f"variant names must differ, got {names}")
        return variants

    @field_validator("baseline", mode="before")
    @classmethod
    def _one_baseline_is_a_list(cls, baseline: Any) -> Any:
        return [baseline] if isinstance(baseline, str) else baseline

    @field_validator("baseline")
    @classmethod
    def _baselines_are_variants(cls, baseline: list[str], info: ValidationInfo) -> list[str]:
        if "variants" not in info.data:  # the variants themselves are invalid, and reported: nothing to check against
            return baseline
        names = [variant.get("name") for variant in info.data["variants"]]
        unknown = [name for name in baseline if name not in names]
        if unknown:
            known = ", ".join(map(str, names)) if names else "none (the sweep has no variants)"
            raise ValueError(f"baseline {unknown[0]!r} is not a variant of this sweep; its variants: {known}")
        return baseline

    @property
    def program(self) -> type[Program]:
        return METHODS[self.method]

    def seed_list(self) -> list[int]:
        if isinstance(self.seeds, SeedRange):
            return list(range(self.seeds.first, self.seeds.first + self.seeds.count))
        return list(self.seeds)

    def seed_count(self) -> int:
        return self.seeds.count if isinstance(self.seeds, SeedRange) else len(self.seeds)

    def metric_name(self) -> str:
        return self.metric.name or next(iter(self.program.metrics))


# ----------------------------------------------------------------- trials
IDENTITY_NEUTRAL_DEFAULTS: dict[str, Any] = {
    "noise_release": "2.1",
    "window_counts": "episodes",
    "relabel_restart": "chunk",
    "reinitialize": False,
    "keep_function": False,
    "init_std_scale": 0.5,
    "epistemic_terms": "means_and_variances",
    "planner_seed_offset": 0,
    "contact_margin": "sum",
    "best_from": "step",
    "layout": "wide",
    "unit_quaternion": False,
    "frozen.task_options": {},
    "aleatoric_states": "particles",
    "frozen.aleatoric_states": ["particles"],
    "refit_epochs": 0,
}
"""Settings added after trials had run, at the value that reproduces the earlier behaviour (by field name at
any depth of a method's settings, or by dotted path where the name alone is ambiguous). They are left out of
a trial's key at that value, so that adding a setting does not change the identity of trials already run
(and ``--resume`` still finds them). Where the new default changed the behaviour (APEX's ``window_counts`` and
``relabel_restart``; ``keep_function``; ``noise_release``), trials of the new default get new keys and the old
trials stay reachable by setting the old value."""


def _is_neutral(path: str, key: str, value: Any) -> bool:
    for name in (f"{path}{key}", key):
        if name in IDENTITY_NEUTRAL_DEFAULTS and value == IDENTITY_NEUTRAL_DEFAULTS[name]:
            return True
    return False


def _without_neutral_defaults(settings: Any, path: str = "") -> Any:
    if isinstance(settings, dict):
        return {
            key: _without_neutral_defaults(value, f"{path}{key}.")
            for key, value in settings.items()
            if not _is_neutral(path, key, value)
        }
    if isinstance(settings, list):
        return [_without_neutral_defaults(value, path) for value in settings]
    return settings


class TrialConfig(BaseModel):
    """Everything that determines a trial's result (resources do not)."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False, frozen=True)

    method: str
    task: str
    settings: SerializeAsAny[MethodSettings]
    seed: int = Field(ge=0)

    def canonical(self) -> dict[str, Any]:
        return {
            "method": self.method,
            "task": self.task,
            "settings": _without_neutral_defaults(self.settings.model_dump(mode="json")),
            "seed": self.seed,
        }

    def key(self) -> str:
        """Hash of the resolved config and seed: a trial's identity across runs and resumes."""
        canonical = json.dumps(self.canonical(), sort_keys=True, separators=(",", ":"))
        return hashlib.sha256(canonical.encode()).hexdigest()[:16]

    def flat(self) -> dict[str, Any]:
        """Dotted-path view for MLflow params (planner.budget, task_options.flip_penalty, ...)."""
        flat: dict[str, Any] = {"method": self.method, "task": self.task, "seed": self.seed}
        flat.update(_flatten(self.settings.model_dump(mode="json")))
        return flat

    def spec(self) -> TrialSpec:
        return TrialSpec(self.method, self.task, self.settings, self.seed)

    @classmethod
    def from_canonical(cls, data: dict[str, Any]) -> TrialConfig:
        """Rebuild a trial from :meth:`canonical` (e.g. as recorded in its run)."""
        settings = METHODS[data["method"]].Settings.model_validate(data["settings"])
        return cls(method=data["method"], task=data["task"], settings=settings, seed=data["seed"])


def _flatten(tree: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    flat: dict[str, Any] = {}
    for key, value in tree.items():
        if isinstance(value, dict) and value:
            flat.update(_flatten(value, f"{prefix}{key}."))
        else:
            flat[f"{prefix}{key}"] = value
    return flat


class Trial(NamedTuple):
    """One concrete run of a sweep."""

    key: str
    """Trial key (:meth:`TrialConfig.key`)."""
    config: TrialConfig
    """The resolved configuration."""
    overrides: dict[str, Any]
    """The swept parameter values of this trial (for display and grouping)."""
    variant: str | None
    """The variant the trial belongs to, if the sweep has variants."""


class LoadedSweep(NamedTuple):
    """A validated sweep with its source and expansion."""

    sweep: Sweep
    trials: list[Trial]
    text: str
    """The YAML as written."""
    path: Path
    file_hash: str
    """sha256 of the YAML text (first 16 hex digits)."""
    references: list[Reference]
    """The published figures the sweep's results are compared with."""


# ---------------------------------------------------------- dotted paths
def _is_mapping(annotation: Any) -> bool:
    return annotation is dict or typing.get_origin(annotation) is dict


def top_level_paths(method: str) -> tuple[str, ...]:
    return ("task", "algorithm") if method == "mpc" else ("task",)


def settings_paths(model: type[BaseModel], prefix: str = "") -> list[str]:
    """Every dotted path into a settings model (groups end in '.<key>' for free-form mappings)."""
    paths = []
    for name, field in model.model_fields.items():
        inner = submodel(field.annotation)
        if inner is not None:
            paths.extend(settings_paths(inner, f"{prefix}{name}."))
        elif _is_mapping(field.annotation):
            paths.append(f"{prefix}{name}.<key>")
        else:
            paths.append(f"{prefix}{name}")
    return paths


def parameter_path_problem(path: str, method: str) -> str | None:
    """Why ``path`` cannot be set by a parameter or variant of a ``method`` sweep, or None."""
    if path in top_level_paths(method):
        return None
    if path == "algorithm":
        return "'algorithm' applies to method mpc; set planner.algorithm in this method's settings"
    model: type[BaseModel] = METHODS[method].Settings
    parts = path.split(".")
    for depth, part in enumerate(parts):
        fields = model.model_fields
        if part not in fields:
            where = ".".join(parts[:depth])
            known = [f"{where}.{f}" if where else f for f in fields]
            if method == "mpc" and path == "planner.algorithm":
                return "sweep 'algorithm' (top level), not planner.algorithm"
            hint = closest_hint(path, [*known, *top_level_paths(method)])
            scope = f" in {where}" if where else ""
            return f"unknown parameter path {path!r}{hint}: no field {part!r}{scope} of method {method}"
        annotation = fields[part].annotation
        rest = parts[depth + 1 :]
        if not rest:
            if method == "mpc" and path == "planner.algorithm":
                return "sweep 'algorithm' (top level), not planner.algorithm"
            return None
        inner = submodel(annotation)
        if inner is not None:
            model = inner
            continue
        if _is_mapping(annotation):
            return None if len(rest) == 1 else f"{'.'.join(parts[: depth + 2])} takes a value, not nested keys"
        return f"{'.'.join(parts[: depth + 1])} is a single value; it has no field {rest[0]!r}"
    return None


# --------------------------------------------------------------- loading
UNCHECKED_TRIALS = "each trial's settings (the base with its variant, grid values and seed, resolved for its task)"
"""What is not checked while the sweep's own keys or the method's settings have problems."""


def load_sweep(path: str | Path) -> LoadedSweep:
    """Read, validate and expand a sweep file; raise :class:`SweepError` on any problem."""
    path = Path(path)
    file = str(path)
    text, data, root = read_yaml(path)
    if data is None:
        raise SweepError([SweepProblem(file, 1, "(file)", "empty sweep file; see sweeps/quickstart.yaml")])
    if not isinstance(data, dict):
        raise SweepError([SweepProblem(file, 1, "(file)", f"a sweep is a mapping of keys, got {type(data).__name__}")])
    misread = _booleans_for_numbers(Sweep, data, (), file, lambda loc: node_line(root, loc))
    try:
        sweep = Sweep.model_validate(data)
    except ValidationError as error:
        flagged = {problem.path for problem in misread}  # pydantic's own complaint about the 0 or 1 it read
        problems = [p for p in problems_from(error, file, root, Sweep, data=data) if p.path not in flagged] + misread
        problems += _method_problems(data, file, root) if "base" not in {p.path.split(".")[0] for p in problems} else []
        raise SweepError(sorted_problems(problems), unchecked=UNCHECKED_TRIALS) from None
    problems = misread + _method_problems(data, file, root)
    if problems:
        raise SweepError(sorted_problems(problems), unchecked=UNCHECKED_TRIALS)
    references = _references(sweep, path, root)
    trials = expand(sweep, file, root)
    file_hash = hashlib.sha256(text.encode()).hexdigest()[:16]
    return LoadedSweep(sweep, trials, text, path, file_hash, references)


def _booleans_for_numbers(model: type[BaseModel], data: Any, prefix: tuple[Any, ...], file: str,
                          line: typing.Callable[[tuple[Any, ...]], int]) -> list[SweepProblem]:  # fmt: skip
    """YAML's true or false written where ``model`` takes a number, as located problems."""
    problems = []
    for loc, value in booleans_for_numbers(model, data, prefix):
        path = ".".join(map(str, loc))
        message = f"a number is expected, got {str(value).lower()} (YAML reads true and false as booleans)"
        problems.append(SweepProblem(file, line(loc), path, message))
    return problems


def _references(sweep: Sweep, path: Path, root) -> list[Reference]:
    """The sweep's reference file, read and validated; problems located in the sweep or in the file."""
    if sweep.reference is None:
        return load_references(THESIS)
    reference = (path.parent / sweep.reference).resolve()
    if not reference.is_file():
        line = node_line(root, ("reference",))
        raise SweepError([SweepProblem(str(path), line, "reference", f"reference file {reference} not found")])
    return load_references(reference)


def _method_problems(data: dict[str, Any], file: str, root) -> list[SweepProblem]:
    """Problems of the parts a method's settings decide: base, parameter paths, variants, roles."""
    method = data.get("method", DEFAULT_METHOD)
    if method not in METHODS:
        return []  # reported by the Sweep model
    program = METHODS[method]
    problems: list[SweepProblem] = []
    base = data.get("base") or {}
    if isinstance(base, dict):
        try:
            program.Settings.model_validate(base)
        except ValidationError as error:
            found = problems_from(error, file, root, program.Settings, prefix=("base",))
            if data.get("variants") or data.get("parameters"):
                # A rule across fields (e.g. "no data and no initial_model") may be met by what a variant or a
                # parameter adds; each trial's whole settings are checked again when the trials are expanded.
                found = [problem for problem in found if problem.path != "base"]
            problems += found
        if method == "mpc" and isinstance(base.get("planner"), dict) and "algorithm" in base["planner"]:
            line = node_line(root, ("base", "planner", "algorithm"))
            problems.append(
                SweepProblem(file, line, "base.planner.algorithm", "set the algorithm once, at the top level")
            )
    if data.get("algorithm") is not None and method != "mpc":
        problems.append(SweepProblem(file, node_line(root, ("algorithm",)), "algorithm", (
            f"'algorithm' applies to method mpc; for {method} set base.planner.algorithm"
        )))  # fmt: skip
    parameters = data.get("parameters") or {}
    for path in parameters if isinstance(parameters, dict) else []:
        problem = parameter_path_problem(str(path), method)
        if problem:
            problems.append(SweepProblem(file, node_line(root, ("parameters", path)), f"parameters.{path}", problem))
            continue
        values = parameters[path].get("values") if isinstance(parameters[path], dict) else None
        for value in values if isinstance(values, list) else []:
            problem = _replaced_base_problem(base, str(path), value, f"parameter {path!r}")
            if problem:
                problems.append(
                    SweepProblem(file, node_line(root, ("parameters", path)), f"parameters.{path}", problem)
                )
                break
    variants = data.get("variants") or []
    for index, variant in enumerate(variants if isinstance(variants, list) else []):
        if not isinstance(variant, dict):
            continue
        for key in variant:
            problem = None if key == "name" else parameter_path_problem(str(key), method)
            if problem is None and key != "name":
                problem = _replaced_base_problem(base, str(key), variant[key], f"variant {variant.get('name')!r}")
            if problem:
                problems.append(SweepProblem(file, node_line(root, ("variants", index, key)), str(key), problem))
            elif key in parameters:
                problems.append(SweepProblem(file, node_line(root, ("variants", index, key)), str(key), (
                    f"set both by variant {variant.get('name')!r} and by parameters"
                )))  # fmt: skip
    # A block that is not a mapping is reported by the Sweep model; only its own keys are checked here.
    resources = data.get("resources")
    roles = resources.get("workers") if isinstance(resources, dict) else None
    for role in roles if isinstance(roles, dict) else []:
        if role not in program.role_names:
            known = ", ".join(program.role_names) or "none"
            hint = closest_hint(str(role), program.role_names)
            message = f"method {method} has no role {role!r}{hint}; its roles: {known}"
            line = node_line(root, ("resources", "workers", role))
            problems.append(SweepProblem(file, line, f"resources.workers.{role}", message))
    metric_block = data.get("metric")
    metric = metric_block.get("name") if isinstance(metric_block, dict) else None
    if isinstance(metric, str) and metric not in program.metrics:
        problems.append(SweepProblem(file, node_line(root, ("metric", "name")), "metric.name", (
            f"method {method} reports no metric {metric!r}{closest_hint(str(metric), program.metrics)}; "
            f"its metrics: {', '.join(program.metrics)}"
        )))  # fmt: skip
    return problems


def _replaced_base_problem(base: Any, path: str, value: Any, setter: str) -> str | None:
    """Why setting ``path`` to the mapping ``value`` would silently drop keys ``base`` sets there, or None.

    An override sets its path to its value as a whole (``_set_path``), so a
    variant ``distance: {cap: null}`` replaces base's entire ``distance`` block
    and loses, say, its ``hidden`` sizes: an ablation of one field would change
    others with it. Such an override is refused with the dotted path to write.
    """
    if not isinstance(value, dict):
        return None
    node = base
    for part in path.split("."):
        node = node.get(part) if isinstance(node, dict) else None
    if not isinstance(node, dict):
        return None
    dropped = sorted(str(key) for key in node if key not in value)
    if not dropped:
        return None
    example = f"{path}.{next(iter(value))}" if value else f"{path}.<field>"
    return (
        f"{setter} replaces the whole of base's {path}, dropping {', '.join(f'{path}.{k}' for k in dropped)}; "
        f"to change single fields, set them by dotted path (e.g. {example}), or restate the dropped keys"
    )


def _set_path(config: dict[str, Any], path: str, value: Any) -> None:
    if path == "task":
        config["task"] = value
        return
    if path == "algorithm":
        path = "planner.algorithm"
    *parents, leaf = path.split(".")
    node = config["settings"]
    for part in parents:
        child = node.get(part)
        node[part] = child = dict(child) if isinstance(child, dict) else {}
        node = child
    node[leaf] = value


def _sweep_rng(sweep: Sweep) -> np.random.Generator:
    """Random parameter draws depend only on the sweep's name, so expansions are repeatable."""
    digest = hashlib.sha256(sweep.name.encode()).digest()
    return np.random.default_rng(int.from_bytes(digest[:8], "little"))


def expand(sweep: Sweep, file: str = "<sweep>", root: yaml.Node | None = None) -> list[Trial]:
    """All trials of a sweep, each validated and resolved; raise SweepError on any problem."""
    grid = {p: spec.values for p, spec in sweep.parameters.items() if isinstance(spec, GridParameter)}
    randoms = {p: spec for p, spec in sweep.parameters.items() if isinstance(spec, RandomParameter)}
    grid_points = math.prod(len(v) for v in grid.values()) if grid else 1
    samples = sweep.num_samples if randoms else 1
    variants = sweep.variants or [{}]
    count = len(variants) * grid_points * samples * sweep.seed_count()
    if count > sweep.max_trials:
        where = ("seeds",) if sweep.seed_count() > sweep.max_trials else ("parameters",)
        line = node_line(root, where)
        message = (
            f"the sweep expands to {count:,} trials, above max_trials = {sweep.max_trials}; "
            "shrink the grid or the seeds, or raise max_trials"
        )
        raise SweepError([SweepProblem(file, line, where[0], message)], unchecked=UNCHECKED_TRIALS)

    base = copy.deepcopy(sweep.base)
    if sweep.method == "mpc":
        base.setdefault("planner", {})
        base["planner"] = dict(base["planner"] or {}, algorithm=sweep.algorithm or "icem")
    rng = _sweep_rng(sweep)
    draws = [{p: spec.draw(rng) for p, spec in randoms.items()} for _ in range(samples)]

    trials: list[Trial] = []
    problems: list[SweepProblem] = []
    seen: set[str] = set()
    combinations = list(itertools.product(*grid.values())) if grid else [()]
    for index, variant in enumerate(variants):
        # Where each override comes from in the YAML, to locate its errors.
        variant_overrides = {path: value for path, value in variant.items() if path != "name"}
        sources = {path: ("variants", index, path) for path in variant_overrides}
        sources |= {path: ("parameters", path) for path in sweep.parameters}
        for combination, draw in itertools.product(combinations, draws):
            overrides = variant_overrides | dict(zip(grid, combination)) | draw
            for seed in sweep.seed_list():
                config = {"task": sweep.task, "settings": copy.deepcopy(base), "seed": seed}
                for path, value in overrides.items():
                    _set_path(config, path, value)
                trial = _resolve_trial(sweep.method, config, sources, file, root, problems)
                if trial is None:
                    continue
                key = trial.key()
                if key in seen:
                    continue  # identical configurations (e.g. a repeated grid value) run once
                seen.add(key)
                trials.append(Trial(key, trial, overrides, variant.get("name")))
    if problems:
        raise SweepError(sorted_problems(problems))
    return trials


def _resolve_trial(method: str, config, sources, file, root, problems) -> TrialConfig | None:
    """Validate and resolve one trial's config; on failure add located problems and return None.

    ``sources`` maps each overridden path to its location in the YAML (a
    parameter or a variant), so that an invalid value is reported where it
    was written.
    """
    program = METHODS[method]

    def blame(path: str) -> int:
        for parameter, location in sources.items():
            target = "planner.algorithm" if parameter == "algorithm" else parameter
            if path == target or path.startswith(target + "."):
                return node_line(root, location)
        if path == "task":  # set at the top level when no parameter or variant sets it
            return node_line(root, ("task",))
        return node_line(root, ("base", *path.split(".")))

    task = config["task"]
    if not isinstance(task, str) or task not in TASKS:
        problems.append(SweepProblem(file, blame("task"), "task", unknown_task_message(str(task))))
        return None
    problem = program.task_problem(TASKS[task])
    if problem:
        problems.append(SweepProblem(file, blame("task"), "task", problem))
        return None

    planner = config["settings"].get("planner")
    if isinstance(planner, dict) and all(planner.get(key) is not None for key in ("budget", "iterations", "population")):
        message = (
            f"budget {planner['budget']} would be ignored: iterations and population are both given and fix what "
            "is spent; drop the budget, or one of iterations and population to have the other chosen to spend it"
        )
        problems.append(SweepProblem(file, blame("planner.budget"), "planner.budget", message))
        return None

    def report(error: ValidationError, prefix: str, task_options: bool = False) -> None:
        for item in error.errors():
            path = ".".join([prefix, *map(str, item["loc"])] if prefix else map(str, item["loc"])) or prefix or "base"
            message = item["msg"].removeprefix("Value error, ")
            if item["type"] == "extra_forbidden" and task_options:
                message = unknown_option_message(task, str(item["loc"][-1]))
            problems.append(SweepProblem(file, blame(path), path, message))

    settings = config["settings"]
    options = settings.get("task_options")
    if options is not None and not (isinstance(options, dict) and all(isinstance(k, str) for k in options)):
        message = f"task_options is a mapping of option names to values, e.g. {{noise_std: 2.0}}, got {options!r}"
        problems.append(SweepProblem(file, blame("task_options"), "task_options", message))
        return None
    def located(loc: tuple[Any, ...]) -> int:
        return blame(".".join(map(str, loc)))

    misread = _booleans_for_numbers(program.Settings, settings, (), file, located)
    misread += _booleans_for_numbers(TASKS[task].Options, options, ("task_options",), file, located)
    if misread:
        problems.extend(misread)
        return None
    try:
        task_instance = make_task(task, options)
    except ValidationError as error:
        report(error, "task_options", task_options=True)
        return None
    try:
        validated = program.Settings.model_validate(settings)
        resolved = program.resolve(validated, task_instance)
        resolved = resolved.model_copy(update={"task_options": task_instance.options.model_dump()})
    except ValidationError as error:
        report(error, "")
        return None
    except ValueError as error:  # a resolution that the task rules out
        problems.append(SweepProblem(file, blame("task"), "task", str(error)))
        return None
    return TrialConfig(method=method, task=task, settings=resolved, seed=config["seed"])


def sweep_json_schema(builtin_only: bool = False) -> dict[str, Any]:
    """JSON Schema of sweep files, for editor completion and validation.

    ``base`` takes the settings of the sweep's method: one conditional branch
    per method (mpc also when ``method`` is left out). ``builtin_only`` leaves
    plugin methods out (the schema shipped in sweeps/).
    """
    methods = {name: METHODS[name] for name in (BUILTIN_METHODS if builtin_only else METHODS)}
    schema = Sweep.model_json_schema()
    method = schema["properties"]["method"]
    method.pop("const", None)
    method["enum"] = list(methods)
    definitions = schema.setdefault("$defs", {})
    branches = []
    for name, program in methods.items():
        settings_schema = program.Settings.model_json_schema(ref_template="#/$defs/{model}")
        definitions.update(settings_schema.pop("$defs", {}))
        definitions[program.Settings.__name__] = settings_schema
        condition: dict[str, Any] = {"properties": {"method": {"const": name}}, "required": ["method"]}
        if name == DEFAULT_METHOD:
            condition = {"anyOf": [condition, {"not": {"required": ["method"]}}]}
        branches.append(
            {"if": condition, "then": {"properties": {"base": {"$ref": f"#/$defs/{program.Settings.__name__}"}}}}
        )
    schema["allOf"] = branches
    schema["$schema"] = "https://json-schema.org/draft/2020-12/schema"
    schema["title"] = "icemlab sweep"
    return schema
