"""The program protocol: how a method of the thesis runs as a trial of rounds.

Every chapter's method is a :class:`Program`. A trial sets it up, runs one
*round* at a time (a unit of work worth keeping: an MPC episode segment, an
APEX iteration, an MBRL iteration, a block of learner updates), and after each
round takes its state for a checkpoint; a restarted trial restores the last
checkpoint and continues with the next round, so nothing before it is run or
logged twice.

A program declares the *roles* it needs as data (:class:`RoleSpec`: name,
worker class, count, CPUs each) and talks to them through :class:`RoleGroup`,
a plain Python interface. The orchestrator hands it groups of Ray actors;
tests hand it :class:`LocalRoleGroup`, the same worker classes in-process.
Nothing here imports Ray or MLflow.
"""

from __future__ import annotations

import re
import threading
from abc import ABC, abstractmethod
from collections.abc import Callable, Mapping, Sequence
from typing import Any, ClassVar, NamedTuple, Protocol

from pydantic import BaseModel, ConfigDict, ValidationError
from pydantic_core import InitErrorDetails, PydanticCustomError


class MethodSettings(BaseModel):
    """Settings of a method, as a sweep file's ``base`` writes them; every field is sweepable by its dotted path."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False, frozen=True, use_attribute_docstrings=True)

    task_options: dict[str, Any] = {}
    """Switches of the task (see `icemlab tasks`), e.g. flip_penalty, velocity_term."""


def located_error(loc: tuple[Any, ...], message: str, value: Any = None) -> ValidationError:
    """A ValidationError of a method's settings at ``loc``, for what only the task rules out (sweep files
    report it at the line of that setting)."""
    message = message.replace("{", "(").replace("}", ")")
    detail = InitErrorDetails(type=PydanticCustomError("task_mismatch", message), loc=loc, input=value)
    return ValidationError.from_exception_data("MethodSettings", [detail])


class TrialSpec(NamedTuple):
    """Everything a program needs to know about its trial."""

    method: str
    """Registry name of the method."""
    task: str
    """Registry name of the task."""
    settings: MethodSettings
    """The method's resolved settings."""
    seed: int
    """The trial seed; all randomness of the trial derives from it."""


class RoleSpec(NamedTuple):
    """A role a program needs: ``count`` workers of one class, each holding ``cpus`` CPUs."""

    name: str
    """Name of the role, e.g. ``simulation``, ``relabel``, ``ensemble_trainer``."""
    worker: type
    """Worker class (in workers/), built in an actor or in-process with ``kwargs``."""
    count: int
    """Number of workers."""
    cpus: float
    """CPUs each worker holds (its native or torch threads follow from them)."""
    kwargs: Mapping[str, Any] = {}
    """Constructor arguments of the worker."""
    stateful: bool = False
    """A stateless worker's calls are pure: after a crash the call is retried on a restarted worker. A stateful
    worker's loss loses the round in flight: the worker is restarted empty, the program is restored from the
    state after its last completed round, and the round runs again."""
    gpus: float = 0.0
    """GPUs each worker holds."""
    state_loader: str = "load_state_dict"
    """A stateful worker's method that hands it its state. A worker the service restarted after a loss between
    calls refuses every other call (RoleWorkerLost) until this one has run, so it never works on from nothing."""


_LOST_ROLE = re.compile(r"a worker of role '([^']+)' was lost: ")


class RoleWorkerLost(RuntimeError):
    """A role's worker process died during a call; role groups whose workers live in other processes raise it.

    The worker is restarted without its state, so the round in flight cannot go on: the trial's runner
    restores the program from its last completed round and runs the round again.
    """

    def __init__(self, role: str, cause: str):
        super().__init__(f"a worker of role {role!r} was lost: {cause}")
        self.role = role
        self.cause = cause

    @staticmethod
    def role_in(message: str) -> str | None:
        """The role a RoleWorkerLost's message names (as the runner reports a recovery), None for another text."""
        found = _LOST_ROLE.match(message)
        return found[1] if found else None

    def __reduce__(self):  # travels between processes inside Ray's task errors, with what the runner noted on it
        return type(self), (self.role, self.cause), self.__dict__


class Pending(Protocol):
    """A call under way on a worker."""

    def result(self) -> Any: ...

    def done(self) -> bool:
        """Whether the result is ready; never waits (progress counts finished calls with it)."""
        ...


class RoleGroup(Protocol):
    """The workers of one role, seen by a program."""

    name: str
    size: int

    def submit(self, member: int, method: str, *args: Any) -> Pending:
        """Start ``method(*args)`` on worker ``member``; results are collected with ``.result()``."""

    def map(self, method: str, arguments: Sequence[tuple]) -> list[Any]:
        """Run ``method(*args)`` for every tuple, spread over the workers in parallel; results in order."""

    def share(self, value: Any) -> Any:
        """Put a large value (weights, a dataset) once where every worker can read it; pass the result as an
        argument instead of the value. Values that workers report on should carry their own version."""


class _Done:
    def __init__(self, value: Any):
        self.value = value

    def result(self) -> Any:
        return self.value

    def done(self) -> bool:
        return True


class _Deferred:
    """An in-process call, run when its result is asked for (as a remote call would still be running)."""

    def __init__(self, call: Callable[[], Any]):
        self._call = call
        self._done: _Done | None = None

    def result(self) -> Any:
        if self._done is None:
            self._done = _Done(self._call())
        return self._done.value

    def done(self) -> bool:
        return self._done is not None


class LocalRoleGroup:
    """A role's workers built in this process: for tests and in-process runs."""

    def __init__(self, name: str, workers: Sequence[Any]):
        self.name = name
        self.workers = list(workers)
        self.size = len(self.workers)

    @classmethod
    def build(cls, spec: RoleSpec) -> LocalRoleGroup:
        return cls(spec.name, [spec.worker(**spec.kwargs) for _ in range(spec.count)])

    def submit(self, member: int, method: str, *args: Any) -> Pending:
        bound = getattr(self.workers[member], method)
        return _Deferred(lambda: bound(*args))

    def map(self, method: str, arguments: Sequence[tuple]) -> list[Any]:
        if not self.workers:
            raise RuntimeError(f"role {self.name!r} has no workers")
        return [getattr(self.workers[i % self.size], method)(*args) for i, args in enumerate(arguments)]

    def share(self, value: Any) -> Any:
        return value


class Artifact(NamedTuple):
    """A file a round produces for the trial's run (a plot, a data file)."""

    path: str
    """Path inside the run's artifacts, e.g. ``episodes/episode_000.png``."""
    data: bytes
    """The file's content."""


class RoundReport(NamedTuple):
    """What one round tells the trial's run."""

    index: int
    """The round's number (0-based)."""
    metrics: Mapping[str, float]
    """Round-level metrics, logged at ``step``."""
    step: int
    """MLflow step of ``metrics`` (e.g. the episode or iteration index)."""
    series: Mapping[str, Sequence[float]] = {}
    """Per-step metrics of the round (e.g. per environment step), logged at steps ``series_start + t``."""
    series_start: int = 0
    """Step of the first value of every series."""
    artifacts: Sequence[Artifact] = ()
    """Files for the run."""
    done: bool = False
    """Whether this was the trial's last round."""
    summary: Mapping[str, float] = {}
    """With the last round: the trial's headline figures (e.g. mean_return, success_rate)."""
    seconds: float = 0.0
    """Wall-clock seconds the round took (set by the runner; plans of later sweeps are estimated from it)."""


class Progress(NamedTuple):
    """Where a program is within its current round (read while the round runs)."""

    fraction: float
    """Share of the current round done, in [0, 1]."""
    text: str
    """A few words for the progress line, e.g. ``ep 2/3 step 140/300``."""


class Program(ABC):
    """A method of the thesis as a trial of rounds.

    Args:
        trial: the trial's method, task, settings and seed.
        roles: a :class:`RoleGroup` per role of :meth:`roles`.
        cpus: CPUs held by the process that runs the program.
    """

    name: ClassVar[str]
    """Registry name, as sweep files write it under ``method:``."""
    Settings: ClassVar[type[MethodSettings]]
    """The method's settings model."""
    description: ClassVar[str] = ""
    """One line for the command line's help."""
    metrics: ClassVar[dict[str, str]] = {}
    """Headline figures a sweep can be summarised by (``metric.name``) -> the summary key that holds it."""
    label_paths: ClassVar[dict[str, tuple[str, ...]]] = {}
    """The labels of :meth:`labels` -> the settings paths each one shows (reports group by labels, then by
    the other swept paths)."""
    curves: ClassVar[tuple[str, ...]] = ()
    """Metrics that reports draw as curves against their step, one line per configuration (mean over seeds)."""
    curve_step: ClassVar[str] = "step"
    """What the step of those curves counts (the reports' x-axis label)."""

    @classmethod
    def report_plots(cls, files: list[str]) -> list[str]:
        """Which of a finished trial's plot artifacts (paths under ``plots/``) a report copies next to its own
        figures, so that one folder shows each trial's pictures; none by default."""
        return []
    independent_episodes: ClassVar[bool] = False
    """Whether a trial's episodes are independent draws of the method's outcome (their own seeds, nothing
    learned between them), so that a success rate pools over all episodes of all seeds. Episodes of one
    trained policy or model share it: the seed is then the unit, and rates are averaged per seed."""
    paired_episodes: ClassVar[bool] = False
    """Whether episode i of a trial starts alike (state, layout, random streams) in every configuration run with
    the trial's seed, and logs each headline metric per episode at step i: reports then compare a variant with
    its baseline episode by episode rather than seed by seed."""
    role_names: ClassVar[tuple[str, ...]] = ()
    """Names of the roles :meth:`roles_for` may declare (sweeps size them under ``resources.workers``)."""

    def __init__(self, trial: TrialSpec, roles: Mapping[str, RoleGroup], cpus: int):
        self.trial = trial
        self.roles = roles
        self.cpus = cpus
        self._progress_lock = threading.Lock()
        self._progress = Progress(0.0, "starting")

    # --------------------------------------------------------- declaration
    @classmethod
    def resolve(cls, settings: MethodSettings, task: Any) -> MethodSettings:
        """Make every default that depends on the task concrete (e.g. the planner's colored-noise beta)."""
        return settings

    @classmethod
    def task_problem(cls, task_class: type) -> str | None:
        """Why the method cannot run a task, or None (default: any ground-truth MuJoCo task)."""
        from workers.tasks import GroundTruthTask

        if not issubclass(task_class, GroundTruthTask):
            return f"method {cls.name} needs a MuJoCo ground-truth task; {task_class.name} is not one"
        return None

    @classmethod
    def roles_for(cls, trial: TrialSpec, unit_cpus: int, counts: Mapping[str, int]) -> list[RoleSpec]:
        """The roles this trial needs.

        Args:
            unit_cpus: the CPUs the scheduler gives one unit of work (the runner,
                a simulation worker) for the trial's share of the machine.
            counts: worker counts the sweep's ``resources`` asks for, by role name.
        """
        return []

    @classmethod
    def runner_cpus(cls, trial: TrialSpec, unit_cpus: int) -> int:
        """CPUs of the process that runs the program itself."""
        return unit_cpus

    @classmethod
    def labels(cls, trial: TrialSpec) -> dict[str, str]:
        """Short tags that identify the trial in MLflow and on the progress line (beyond task and seed)."""
        return {}

    @classmethod
    @abstractmethod
    def planned_rounds(cls, trial: TrialSpec) -> int:
        """Rounds of the whole trial (for progress and ETA; a trial may end sooner by reporting done)."""

    @classmethod
    def round_work(cls, trial: TrialSpec, counts: Mapping[str, int]) -> list[float]:
        """Each round's expected wall time relative to the others, one weight per planned round; times to go
        weigh the rounds still to run by it (default: all rounds alike).

        Args:
            counts: worker counts the sweep's ``resources`` asks for, by role name (as for :meth:`roles_for`).
        """
        return [1.0] * cls.planned_rounds(trial)

    @classmethod
    def label_text(cls, labels: Mapping[str, str]) -> list[str]:
        """The labels as short words for run names and report rows."""
        return [value if not value.replace(".", "").isdigit() else f"{key}={value}" for key, value in labels.items()]

    @classmethod
    def work(cls, trial: TrialSpec) -> float:
        """The trial's amount of work in the method's unit (default: rounds), for time estimates."""
        return float(cls.planned_rounds(trial))

    @classmethod
    def calibrate(cls, trial: TrialSpec, cpus: int) -> float | None:
        """Core-seconds per unit of :meth:`work`, measured in a few seconds here; None if the method cannot."""
        return None

    # --------------------------------------------------------------- run
    def total_rounds(self) -> int:
        return self.planned_rounds(self.trial)

    @abstractmethod
    def run_round(self, index: int) -> RoundReport:
        """Run round ``index`` (rounds run in order, continuing after a restore) and report it."""

    @abstractmethod
    def state_dict(self) -> dict[str, Any]:
        """Everything needed to continue after the last completed round, as a checkpoint tree."""

    @abstractmethod
    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Continue from a :meth:`state_dict` (in a fresh program of the same trial)."""

    def close(self) -> None:  # noqa: B027 - most programs hold nothing to release
        """Release environments and thread pools."""

    # ----------------------------------------------------------- progress
    def progress(self) -> Progress:
        """Within-round progress; safe to call from another thread while a round runs."""
        with self._progress_lock:
            return self._progress

    def set_progress(self, fraction: float, text: str) -> None:
        with self._progress_lock:
            self._progress = Progress(min(max(fraction, 0.0), 1.0), text)


def run_locally(program_class: type[Program], trial: TrialSpec, unit_cpus: int = 1) -> list[RoundReport]:
    """Run a whole trial in this process with in-process roles (tests, debugging)."""
    roles = {spec.name: LocalRoleGroup.build(spec) for spec in program_class.roles_for(trial, unit_cpus, {})}
    program = program_class(trial, roles, unit_cpus)
    reports = []
    try:
        for index in range(program.total_rounds()):
            reports.append(program.run_round(index))
            if reports[-1].done:
                break
    finally:
        program.close()
    return reports
