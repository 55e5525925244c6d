"""Sweep files: schema, YAML loading with located errors, expansion into trials.

A sweep YAML names a task and an algorithm, a base configuration, the
parameters to vary (grid ``values`` or random ``distribution`` draws over
dotted paths such as ``planner.budget``) and the seeds. Loading validates the
file and every concrete trial it expands to before anything runs; problems come
back as :class:`SweepError` with one ``FILE:LINE: path: message`` per problem.
"""

from __future__ import annotations

import difflib
import hashlib
import itertools
import json
import math
from collections.abc import Iterable
from pathlib import Path
from typing import Annotated, Any, Literal, NamedTuple

import numpy as np
import yaml
from pydantic import (
    AfterValidator,
    BaseModel,
    ConfigDict,
    Field,
    ValidationError,
    ValidationInfo,
    field_validator,
    model_validator,
)

from workers.planning.config import Algorithm, PlannerConfig
from workers.tasks import TASKS, make_task, unknown_task_message

DEFAULT_MAX_TRIALS = 1000


class _UserModel(BaseModel):
    """Base of everything a user writes: unknown keys are errors."""

    model_config = ConfigDict(extra="forbid", use_attribute_docstrings=True)


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
            if self.low > self.high:
                raise ValueError(f"low ({self.low}) is above high ({self.high})")
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


class TrialSettings(_UserModel):
    """Settings shared by every trial of the sweep (the base that parameters override)."""

    planner: PlannerConfig = PlannerConfig()
    """The planner: budget, horizon and the switches of the CEM family (see PlannerConfig)."""
    task_options: dict[str, Any] = {}
    """Switches of the task's planning cost (see `icemlab tasks`), e.g. flip_penalty, velocity_term."""
    episodes: int = Field(1, ge=1)
    """MPC episodes per trial (each with its own seed derived from the trial seed)."""
    max_steps: int | None = Field(None, ge=1)
    """Cut episodes to this many steps (smoke runs); default: the task's episode length."""


class Resources(_UserModel):
    """How a trial uses the machine or cluster."""

    simulation_workers: int = Field(1, ge=1)
    """SimulationWorker actors per trial; a trial's batch is split between them."""
    threads_per_worker: int | None = Field(None, ge=1)
    """Native rollout threads (and Ray CPUs) per simulation worker. Default: the node's CPUs / concurrent trials."""


class Metric(_UserModel):
    """The figure a sweep is summarised by."""

    name: Literal["episode_return", "success"] = "episode_return"
    """episode_return (sum of rewards) or success (success rate, tasks with a success criterion)."""
    mode: Literal["max", "min"] = "max"
    """Whether higher is better."""


class Tracking(_UserModel):
    """Where results go in MLflow."""

    experiment: str | None = None
    """MLflow experiment; default: the sweep name."""
    tags: dict[str, str] = {}
    """Extra tags on the sweep's parent run."""


def _check_parameter_path(path: str) -> str:
    problem = parameter_path_problem(path)
    if problem:
        raise ValueError(problem)
    return path


ParameterPath = Annotated[str, AfterValidator(_check_parameter_path)]
"""A dotted path that a sweep may vary."""


def _check_variant_key(key: str) -> str:
    return key if key == "name" else _check_parameter_path(key)


Variant = dict[Annotated[str, AfterValidator(_check_variant_key)], Any]
"""A named set of overrides: ``name`` plus dotted paths and their values."""


class Sweep(_UserModel):
    """A sweep file: what to run, over which parameters and seeds, and how."""

    name: str = Field(pattern=r"^[A-Za-z0-9][A-Za-z0-9_.\-]*$", max_length=100)
    """Sweep name (letters, digits, _ . -); names the MLflow experiment by default."""
    task: str
    """Task name, e.g. halfcheetah_running (see `icemlab tasks`)."""
    algorithm: Algorithm = "icem"
    """Planner of the CEM family: icem, cem, cem_mpc or cem_pets."""
    base: TrialSettings = TrialSettings()
    """Configuration shared by all trials."""
    parameters: dict[ParameterPath, GridParameter | RandomParameter] = {}
    """Parameters to vary, by dotted path (task, algorithm, planner.<field>, episodes, max_steps)."""
    variants: list[Variant] = []
    """Named sets of overrides run side by side, e.g. ablations (thesis Fig. 7):
    [{name: full}, {name: no-colored-noise, planner.noise_beta: 0}]. Combined with every grid point and seed."""
    num_samples: int = Field(1, ge=1)
    """Draws of the random parameters (each combined with every grid point and seed)."""
    seeds: list[int] = Field([0], min_length=1)
    """Seeds; every configuration runs once per seed."""
    metric: Metric = Metric()
    """The figure summarising each configuration in reports."""
    resources: Resources = Resources()
    """CPU and worker layout of each trial."""
    retries: int = Field(1, ge=0, le=10)
    """How often a failed trial is retried before it is marked FAILED."""
    max_trials: int = Field(DEFAULT_MAX_TRIALS, ge=1)
    """Refuse sweeps that expand to more trials than this (guards against runaway grids)."""
    tracking: Tracking = Tracking()
    """MLflow experiment and tags."""

    @field_validator("variants")
    @classmethod
    def _variants_are_named_and_distinct(cls, variants: list[dict[str, Any]], info: ValidationInfo):
        names = [variant.get("name") for variant in variants]
        if any(not isinstance(name, str) or not name for name in names):
            raise ValueError("every variant needs a 'name'")
        if len(set(names)) != len(names):
            raise ValueError(f"variant names must differ, got {names}")
        parameters = info.data.get("parameters") or {}
        for variant in variants:
            clash = set(variant) & set(parameters)
            if clash:
                raise ValueError(f"{sorted(clash)} set both by variant {variant['name']!r} and by parameters")
        return variants

    @field_validator("task")
    @classmethod
    def _known_task(cls, task: str) -> str:
        if task not in TASKS:
            raise ValueError(unknown_task_message(task))
        return task

    @field_validator("seeds")
    @classmethod
    def _non_negative_seeds(cls, seeds: list[int]) -> list[int]:
        negative = [s for s in seeds if s < 0]
        if negative:
            raise ValueError(f"seeds must be >= 0, got {negative}")
        if len(set(seeds)) != len(seeds):
            raise ValueError("seeds must not repeat (a repeated seed would run the same trial twice)")
        return seeds


# ----------------------------------------------------------------- trials
class TrialConfig(BaseModel):
    """Everything that determines a trial's result (resources do not)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    task: str
    task_options: dict[str, Any]
    planner: PlannerConfig
    episodes: int = Field(ge=1)
    max_steps: int | None = Field(ge=1)
    seed: int = Field(ge=0)

    def key(self) -> str:
        """Hash of the resolved config and seed: a trial's identity across runs and resumes."""
        canonical = json.dumps(self.model_dump(mode="json"), sort_keys=True, separators=(",", ":"))
        return hashlib.sha256(canonical.encode()).hexdigest()[:16]

    def flat(self) -> dict[str, Any]:
        """Dotted-path view for MLflow params."""
        flat = {"task": self.task, "episodes": self.episodes, "max_steps": self.max_steps, "seed": self.seed}
        flat.update({f"task_options.{k}": v for k, v in self.task_options.items()})
        flat.update({f"planner.{k}": v for k, v in self.planner.model_dump().items()})
        return flat


class Trial(NamedTuple):
    """One concrete run of a sweep."""

    key: str
    """Trial key (:meth:`TrialConfig.key`)."""
    index: int
    """Position in the sweep's expansion order."""
    config: TrialConfig
    """The resolved configuration."""
    overrides: dict[str, Any]
    """The swept parameter values of this trial (for display)."""


class SweepProblem(NamedTuple):
    """One problem of a sweep file, located."""

    file: str
    line: int
    path: str
    message: str

    def __str__(self) -> str:
        return f"{self.file}:{self.line}: {self.path}: {self.message}"


class SweepError(Exception):
    """A sweep file that cannot run; ``problems`` lists every located problem."""

    def __init__(self, problems: list[SweepProblem]):
        self.problems = problems
        super().__init__("\n".join(str(p) for p in problems))


class LoadedSweep(NamedTuple):
    """A validated sweep with its source and expansion."""

    sweep: Sweep
    trials: list[Trial]
    text: str
    """The YAML as written."""
    path: Path
    file_hash: str
    """sha256 of the YAML text (first 16 hex digits)."""


# ---------------------------------------------------------- dotted paths
TOP_LEVEL_PATHS = ("task", "algorithm", "episodes", "max_steps")
PLANNER_FIELDS = tuple(PlannerConfig.model_fields)


def parameter_path_problem(path: str) -> str | None:
    """Why ``path`` cannot be swept, or None."""
    if path in TOP_LEVEL_PATHS or (path.startswith("task_options.") and len(path) > len("task_options.")):
        return None  # task options are checked against the task's own options when trials expand
    if path.startswith("planner."):
        field = path.removeprefix("planner.")
        if field == "algorithm":
            return "sweep 'algorithm' (top level), not planner.algorithm"
        if field in PLANNER_FIELDS:
            return None
        return f"unknown planner field {field!r}{_closest_hint(field, PLANNER_FIELDS, 'planner.')}"
    hint = _closest_hint(path, list(TOP_LEVEL_PATHS) + [f"planner.{f}" for f in PLANNER_FIELDS])
    return (
        f"unknown parameter path {path!r}{hint}; "
        "sweepable: task, algorithm, episodes, max_steps, planner.<field>, task_options.<option>"
    )


# ------------------------------------------------------------ locations
def _node_line(root: yaml.Node | None, loc: tuple[Any, ...]) -> int:
    """1-based line of the deepest node along ``loc`` that exists in the YAML."""
    node, line = root, (root.start_mark.line + 1 if root is not None else 1)
    for part in loc:
        if isinstance(node, yaml.MappingNode):
            for key, value in node.value:
                if key.value == str(part):
                    line, node = key.start_mark.line + 1, value
                    break
            else:
                return line
        elif isinstance(node, yaml.SequenceNode) and isinstance(part, int) and part < len(node.value):
            node = node.value[part]
            line = node.start_mark.line + 1
        else:
            return line
    return line


def _closest_hint(word: str, candidates: Iterable[str], prefix: str = "") -> str:
    """' (did you mean 'X'?)' for the candidate closest to ``word``, or ''."""
    close = difflib.get_close_matches(word, list(candidates), n=1)
    return f" (did you mean '{prefix}{close[0]}'?)" if close else ""


def _did_you_mean(model: type[BaseModel], loc: tuple[Any, ...], key: str) -> str:
    """A hint for an unknown key, from the fields of the model the key sits in."""
    for part in loc[:-1]:
        field = model.model_fields.get(str(part)) if isinstance(part, str) else None
        annotation = getattr(field, "annotation", None) if field else None
        if isinstance(annotation, type) and issubclass(annotation, BaseModel):
            model = annotation
        else:
            return ""
    return _closest_hint(key, model.model_fields)


def _problems_from(error: ValidationError, file: str, root: yaml.Node | None, prefix=(), line_of=None):
    problems = []
    for item in error.errors():
        loc = tuple(prefix) + tuple(item["loc"])
        # Pydantic names union members in the location; they are not YAML keys.
        loc = tuple(p for p in loc if p not in ("GridParameter", "RandomParameter", "[key]"))
        message = item["msg"].removeprefix("Value error, ")
        if item["type"] == "extra_forbidden":
            message = f"unknown key{_did_you_mean(Sweep, loc, str(loc[-1]))}"
        elif item["type"] == "missing":
            message = "required key is missing"
        line = line_of if line_of is not None else _node_line(root, loc)
        path = ".".join(str(p) for p in loc) or "(file)"
        problems.append(SweepProblem(file, line, path, message))
    return problems


# --------------------------------------------------------------- loading
def load_sweep(path: str | Path) -> LoadedSweep:
    """Read, validate and expand a sweep file; raise :class:`SweepError` on any problem."""
    path = Path(path)
    file = str(path)
    try:
        raw_bytes = path.read_bytes()
    except OSError as error:
        raise SweepError([SweepProblem(file, 1, "(file)", f"cannot read: {error.strerror or error}")]) from None
    if b"\x00" in raw_bytes:
        raise SweepError([SweepProblem(file, 1, "(file)", "binary file, not a YAML sweep")])
    try:
        text = raw_bytes.decode("utf-8")
    except UnicodeDecodeError as error:
        raise SweepError([SweepProblem(file, 1, "(file)", f"not UTF-8 text ({error.reason})")]) from None
    try:
        root = yaml.compose(text, Loader=yaml.SafeLoader)
        data = yaml.safe_load(text)
    except yaml.YAMLError as error:
        mark = getattr(error, "problem_mark", None)
        line = mark.line + 1 if mark is not None else 1
        reason = getattr(error, "problem", None) or str(error)
        context, context_mark = getattr(error, "context", None), getattr(error, "context_mark", None)
        if context and context_mark is not None and context_mark.line + 1 != line:
            reason += f" ({context} on line {context_mark.line + 1})"
        raise SweepError([SweepProblem(file, line, "(yaml)", f"YAML syntax error: {reason}")]) from None
    if data is None:
        raise SweepError([SweepProblem(file, 1, "(file)", "empty sweep file; see sweeps/quickstart.yaml")])
    if not isinstance(data, dict):
        raise SweepError([SweepProblem(file, 1, "(file)", f"a sweep is a mapping of keys, got {type(data).__name__}")])
    try:
        sweep = Sweep.model_validate(data)
    except ValidationError as error:
        raise SweepError(sorted(_problems_from(error, file, root), key=lambda p: p.line)) from None
    planner_input = (data.get("base") or {}).get("planner") or {}
    if "algorithm" in planner_input and planner_input["algorithm"] != sweep.algorithm:
        line = _node_line(root, ("base", "planner", "algorithm"))
        raise SweepError(
            [SweepProblem(file, line, "base.planner.algorithm", "set the algorithm once, at the top level")]
        )
    trials = expand(sweep, data, file, root)
    file_hash = hashlib.sha256(text.encode()).hexdigest()[:16]
    return LoadedSweep(sweep, trials, text, path, file_hash)


def _set_path(config: dict[str, Any], path: str, value: Any) -> None:
    if path == "algorithm":
        config["planner"]["algorithm"] = value
    elif path.startswith("planner."):
        config["planner"][path.removeprefix("planner.")] = value
    elif path.startswith("task_options."):
        config["task_options"][path.removeprefix("task_options.")] = value
    else:
        config[path] = value


def _sweep_rng(sweep: Sweep) -> np.random.Generator:
    """Random parameter draws depend only on the sweep's name, so expansions are repeatable."""
    digest = hashlib.sha256(sweep.name.encode()).digest()
    return np.random.default_rng(int.from_bytes(digest[:8], "little"))


def expand(sweep: Sweep, data: dict[str, Any], file: str = "<sweep>", root: yaml.Node | None = None) -> list[Trial]:
    """All trials of a sweep, each validated and resolved; raise SweepError on any problem."""
    grid = {p: spec.values for p, spec in sweep.parameters.items() if isinstance(spec, GridParameter)}
    randoms = {p: spec for p, spec in sweep.parameters.items() if isinstance(spec, RandomParameter)}
    grid_points = math.prod(len(v) for v in grid.values()) if grid else 1
    samples = sweep.num_samples if randoms else 1
    variants = sweep.variants or [{}]
    count = len(variants) * grid_points * samples * len(sweep.seeds)
    if count > sweep.max_trials:
        line = _node_line(root, ("parameters",))
        raise SweepError(
            [
                SweepProblem(
                    file,
                    line,
                    "parameters",
                    f"the sweep expands to {count} trials, above max_trials = {sweep.max_trials}; "
                    "shrink the grid or raise max_trials",
                )
            ]
        )

    base_planner = dict((data.get("base") or {}).get("planner") or {})
    base_planner["algorithm"] = sweep.algorithm
    rng = _sweep_rng(sweep)
    draws = [{p: spec.draw(rng) for p, spec in randoms.items()} for _ in range(samples)]

    trials: list[Trial] = []
    problems: list[SweepProblem] = []
    seen: dict[str, int] = {}
    combinations = list(itertools.product(*grid.values())) if grid else [()]
    for index, variant in enumerate(variants):
        # Where each override comes from in the YAML, to locate its errors.
        variant_overrides = {path: value for path, value in variant.items() if path != "name"}
        sources = {path: ("variants", index, path) for path in variant_overrides}
        sources |= {path: ("parameters", path) for path in sweep.parameters}
        for combination, draw in itertools.product(combinations, draws):
            overrides = variant_overrides | dict(zip(grid, combination)) | draw
            shown = ({"variant": variant["name"]} if variant else {}) | overrides
            for seed in sweep.seeds:
                config = {
                    "task": sweep.task,
                    "task_options": dict(sweep.base.task_options),
                    "planner": dict(base_planner),
                    "episodes": sweep.base.episodes,
                    "max_steps": sweep.base.max_steps,
                    "seed": seed,
                }
                for path, value in overrides.items():
                    _set_path(config, path, value)
                trial = _resolve_trial(config, sources, file, root, problems)
                if trial is None:
                    continue
                key = trial.key()
                if key in seen:
                    continue  # identical configurations (e.g. a repeated grid value) run once
                seen[key] = len(trials)
                trials.append(Trial(key, len(trials), trial, shown))
    if problems:
        raise SweepError(sorted(dict.fromkeys(problems), key=lambda p: p.line))
    return trials


def _resolve_trial(config, sources, file, root, problems) -> TrialConfig | None:
    """Validate and resolve one trial's config; on failure add located problems and return None.

    ``sources`` maps each overridden path to its location in the YAML (a
    parameter or a variant), so that an invalid value is reported where it
    was written.
    """

    def blame(path: str) -> int:
        for parameter, location in sources.items():
            if (
                path == parameter
                or path.startswith(parameter + ".")
                or (parameter == "algorithm" and path == "planner.algorithm")
            ):
                return _node_line(root, location)
        return _node_line(root, ("base", *path.split(".")))

    task = config["task"]
    if task not in TASKS:
        problems.append(SweepProblem(file, blame("task"), "task", unknown_task_message(str(task))))
        return None

    def report(error: ValidationError, prefix: str, fields: list[str] | None = None) -> None:
        for item in error.errors():
            path = ".".join([prefix, *map(str, item["loc"])] if prefix else map(str, item["loc"])) or prefix
            message = item["msg"].removeprefix("Value error, ")
            if item["type"] == "extra_forbidden" and fields is not None:
                option = str(item["loc"][-1])
                hint = _closest_hint(option, fields)
                message = f"{task} has no option {option!r}{hint}; its options: {', '.join(fields) or 'none'}"
            problems.append(SweepProblem(file, blame(path), path, message))

    try:
        task_instance = make_task(task, config["task_options"])
    except ValidationError as error:
        report(error, "task_options", list(TASKS[task].Options.model_fields))
        return None
    try:
        planner = PlannerConfig.model_validate(config["planner"]).resolved(task_instance.colored_noise_beta)
    except ValidationError as error:
        report(error, "planner")
        return None
    try:
        options = task_instance.options.model_dump()
        return TrialConfig.model_validate({**config, "planner": planner, "task_options": options})
    except ValidationError as error:
        report(error, "")
        return None


def sweep_json_schema() -> dict[str, Any]:
    """JSON Schema of sweep files, for editor completion and validation."""
    schema = Sweep.model_json_schema()
    schema["$schema"] = "https://json-schema.org/draft/2020-12/schema"
    schema["title"] = "icemlab sweep"
    return schema
