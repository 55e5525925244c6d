"""Everything that talks to MLflow (the only module that imports mlflow).

Run tree: one experiment per sweep; a parent run per sweep execution (the YAML,
summary table and plots); a child run per trial (resolved config as params;
trial_key / method / task / seed / variant tags; the metrics of its rounds;
plots, data files and checkpoints as artifacts). Only the driver writes, so
the embedded SQLite store sees exactly one writer.

Identity and resume: a trial is its key (hash of resolved config and seed).
A key with a FINISHED child run is never run or logged again. A trial keeps
one child run through retries, lost processes and ``--resume``: every
restart continues the same run from the trial's last checkpoint, and records
why it restarted (``failures/``). Rounds are logged with a marker metric
(``icemlab.round``); a round whose marker is present is never logged again.

Checkpoints live in the run's artifacts, ``checkpoints/round_NNNNNN/``: the
state file first, then ``manifest.json`` with its size and sha256. A
checkpoint without a manifest (a crash while writing) or whose state does not
match it (truncated, replaced) is skipped for the one before it.
"""

from __future__ import annotations

import json
import logging
import os
import socket
import itertools
import tempfile
import time
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any, NamedTuple

# Keep MLflow quiet and local: no telemetry, no background job runner.
os.environ.setdefault("MLFLOW_DISABLE_TELEMETRY", "true")
os.environ.setdefault("DO_NOT_TRACK", "true")

from mlflow.entities import Metric, Param, RunStatus, RunTag  # noqa: E402
from mlflow.exceptions import MlflowException  # noqa: E402
from mlflow.tracking import MlflowClient  # noqa: E402

from workers.checkpoint import digest  # noqa: E402

# Database set-up messages are not news to the user.
logging.getLogger("mlflow.store.db.utils").setLevel(logging.WARNING)
logging.getLogger("alembic").setLevel(logging.WARNING)

TAG_KIND = "icemlab.kind"
TAG_SWEEP = "icemlab.sweep"
TAG_SWEEP_HASH = "icemlab.sweep_file_hash"
TAG_TRIAL_KEY = "icemlab.trial_key"
TAG_VARIANT = "icemlab.variant"
TAG_ATTEMPTS = "icemlab.attempts"
TAG_ERROR = "icemlab.error"
TAG_ERROR_CLASS = "icemlab.error_class"
TAG_ROUNDS = "icemlab.rounds"
TAG_SUMMARY = "icemlab.summary_logged"
"""Written in one batch with a trial's summary metrics: a driver that dies before the run is closed leaves it, and
the attempt that closes the run then does not log the summary a second time."""
TAG_PLANNED_ROUNDS = "icemlab.planned_rounds"
"""How many rounds the trial has in all (set at every attempt)."""
TAG_ROUND_WORK = "icemlab.round_work"
"""Each round's expected wall time relative to the others, run-length coded (see :func:`encode_round_work`)."""
TAG_FAILED_TRIALS = "icemlab.failed_trials"
TAG_INTERRUPTED = "icemlab.interrupted"
TAG_PLANNED_TRIALS = "icemlab.planned_trials"
"""How many trials the sweep file defines (set when the sweep starts or resumes)."""
TAG_DRIVER = "icemlab.driver"
"""host|pid|start time of the driver of the sweep's current session (a resume refuses while it runs)."""
TAG_SESSION_STARTED = "icemlab.session_started"
"""When the sweep's current session (its start, or its latest resume) began, in seconds since the epoch."""
TAG_OVERRIDE = "icemlab.override."
"""Prefix of the tags that hold a trial's swept values (JSON)."""
TAG_VERSION = "version."
"""Prefix of the tags that hold the package versions a trial ran with."""
TAG_CODE_VERSION = "icemlab.version"
TAG_COMMIT = "icemlab.commit"
TAG_DIRTY = "icemlab.dirty"
TAG_MACHINE = "icemlab.machine."
"""Prefix of the tags that describe the worker a trial ran on (cpu_model, cpus, host)."""
TAG_THREADS = "icemlab.threads_per_worker"
"""The CPUs per unit of work (torch's thread count) of the trial's latest attempt."""
TAG_THREADS_CHANGED = "icemlab.threads_changed"
"""Set when an attempt continued a trial with another thread count than the one before ("2 -> 1")."""
PARAM_THREADS = "resources.threads_per_worker"
"""The run parameter with the thread count of a trial's first attempt."""
TAG_PARENT = "mlflow.parentRunId"
TAG_RUN_NAME = "mlflow.runName"
ROUND_MARKER = "icemlab.round"
"""Metric logged with the last batch of every round, at step = round index."""
ROUND_SECONDS = "icemlab.round_seconds"
"""Wall-clock seconds of every round, at step = round index (sweep plans are estimated from it)."""
CORE_SECONDS_PER_WORK = "icemlab.core_seconds_per_work"
"""A finished trial's CPU cost per unit of its method's work (MPC: per environment step)."""
CHECKPOINTS = "checkpoints"
KEEP_CHECKPOINTS = 3
MAX_BATCH = 1000  # MLflow's limit of metrics per log_batch request
MAX_TAG_LENGTH = 5000

FINISHED = RunStatus.to_string(RunStatus.FINISHED)
FAILED = RunStatus.to_string(RunStatus.FAILED)
KILLED = RunStatus.to_string(RunStatus.KILLED)
RUNNING = RunStatus.to_string(RunStatus.RUNNING)


def this_driver() -> str:
    """host|pid|start of this process, as the sweep's run records its driver (the start tells a reused pid)."""
    return f"{socket.gethostname()}|{os.getpid()}|{process_start(os.getpid())}"


def process_start(pid: int) -> str | None:
    """When process ``pid`` started, as an opaque text that stays the same for its life; None if it is gone."""
    try:  # Linux: field 22 of /proc/PID/stat, in clock ticks since boot (after the command, which may hold spaces)
        return Path(f"/proc/{pid}/stat").read_text().rpartition(")")[2].split()[19]
    except (OSError, IndexError):
        pass
    try:  # elsewhere (macOS): ps tells the start time
        import subprocess

        started = subprocess.run(["ps", "-o", "lstart=", "-p", str(pid)], capture_output=True, text=True, timeout=10)
    except (OSError, subprocess.SubprocessError):
        return None
    return started.stdout.strip() or None


def live_driver(recorded: str | None) -> int | None:
    """The pid of a recorded driver still running on this host; None if it is gone (its pid unused or used by a
    later process), is this process, or runs on another host (whose processes this one cannot see). A check,
    not a lock: two resumes started in the same second can both pass it."""
    host, pid, start = ((recorded or "").split("|") + ["", "", ""])[:3]
    if host != socket.gethostname() or not pid.isdigit() or int(pid) == os.getpid():
        return None
    return int(pid) if start and process_start(int(pid)) == start else None


def encode_round_work(work: Sequence[float]) -> str:
    """Run-length code of per-round weights, e.g. ``0,1*40,13*3`` (a tag holds a few thousand characters; a trial
    may have thousands of rounds, mostly alike)."""
    runs: list[list] = []
    for weight in work:
        if runs and runs[-1][0] == weight:
            runs[-1][1] += 1
        else:
            runs.append([weight, 1])
    return ",".join(f"{weight:g}" + (f"*{count}" if count > 1 else "") for weight, count in runs)


def decode_round_work(text: str) -> list[float] | None:
    """The weights of :func:`encode_round_work`'s code; None for an empty or unreadable one."""
    work: list[float] = []
    try:
        for part in text.split(","):
            weight, _, count = part.partition("*")
            work.extend([float(weight)] * (int(count) if count else 1))
    except ValueError:
        return None
    return work or None


def default_tracking_uri(directory: Path | None = None) -> str:
    """The embedded store: SQLite in the working directory, no server needed."""
    directory = Path.cwd() if directory is None else directory
    return f"sqlite:///{(directory / 'mlflow.db').resolve()}"


def resolve_tracking_uri(uri: str | None) -> str:
    """Explicit URI, else MLFLOW_TRACKING_URI, else the embedded SQLite store."""
    return uri or os.environ.get("MLFLOW_TRACKING_URI") or default_tracking_uri()


def tracking_uri_source(uri: str | None) -> str:
    """Where :func:`resolve_tracking_uri` took the URI from, for messages about it."""
    if uri:
        return "--tracking-uri"
    return "$MLFLOW_TRACKING_URI" if os.environ.get("MLFLOW_TRACKING_URI") else "the default"


def sqlite_path(uri: str) -> Path | None:
    """The database file of an embedded-store URI (``sqlite:///PATH``, without a ``?query``), else None."""
    if not uri.startswith("sqlite:///"):
        return None
    return Path(uri.removeprefix("sqlite:///").partition("?")[0])


class StoreUnavailable(Exception):
    """The tracking store cannot be used; the message says which store and why, in one line."""


STORE_SCHEMES = ("sqlite", "http", "https", "postgresql", "mysql", "mssql")
"""Tracking URI schemes of the stores icemlab writes to (MLflow's file store is in maintenance mode)."""
SERVER_CONNECT_SECONDS = 5.0
"""How long a tracking server gets to accept a connection before the store is called unreachable (MLflow's own
client retries for minutes)."""


def store_problem(uri: str) -> str | None:
    """Why the store ``uri`` names cannot be used, found without opening it, or None.

    Caught here rather than from MLflow: a directory or an unreadable file in place of the SQLite database makes
    MLflow retry for minutes, a server that does not answer likewise, and other schemes fail with a traceback.
    """
    scheme = uri.partition(":")[0].split("+")[0]
    if scheme not in STORE_SCHEMES:
        return (
            f"scheme {scheme!r} is not one of {', '.join(STORE_SCHEMES)}; the embedded store is sqlite:///PATH "
            "(the default: sqlite:///./mlflow.db), a server is http://HOST:PORT"
        )
    database = sqlite_path(uri)
    if database is not None and database.exists():
        if not database.is_file():
            return f"{database} is not a file"
        if not os.access(database, os.R_OK | os.W_OK):
            return f"{database} cannot be read and written by this user"
        with open(database, "rb") as file:
            header = file.read(16)
        if header and header != b"SQLite format 3\x00":
            return f"{database} is not an SQLite database"
    if scheme in ("http", "https"):
        from urllib.parse import urlsplit

        address = urlsplit(uri)
        port = address.port or (443 if scheme == "https" else 80)
        try:
            socket.create_connection((address.hostname or "", port), timeout=SERVER_CONNECT_SECONDS).close()
        except OSError as error:
            reason = error.strerror or error
            return f"no server answers at {address.hostname}:{port} ({reason}); start it or fix the URI"
    return None


class SweepRun(NamedTuple):
    """A sweep's parent run, as found in MLflow."""

    run_id: str
    name: str
    status: str
    experiment_id: str
    tags: dict[str, str]
    metrics: dict[str, float]

    @property
    def planned_trials(self) -> int | None:
        """Trials the sweep file defines; None for runs recorded before the count was."""
        value = self.tags.get(TAG_PLANNED_TRIALS)
        return int(value) if value and value.isdigit() else None

    @property
    def session_started(self) -> float | None:
        """When the current session (start or latest resume) began, seconds since the epoch; None for runs
        recorded before it was."""
        try:
            return float(self.tags[TAG_SESSION_STARTED])
        except (KeyError, ValueError):
            return None


class TrialRun(NamedTuple):
    """A trial's child run, as found in MLflow."""

    run_id: str
    trial_key: str
    status: str
    name: str
    params: dict[str, str]
    tags: dict[str, str]
    metrics: dict[str, float]
    end_time: float | None = None
    """When the run ended, in seconds since the epoch; None while it runs."""

    @property
    def variant(self) -> str | None:
        return self.tags.get(TAG_VARIANT)

    @property
    def error(self) -> str | None:
        return self.tags.get(TAG_ERROR)

    @property
    def error_class(self) -> str | None:
        return self.tags.get(TAG_ERROR_CLASS)

    @property
    def attempts(self) -> int:
        return int(self.tags.get(TAG_ATTEMPTS, "1"))

    @property
    def rounds(self) -> int:
        """Rounds logged so far."""
        return int(self.tags.get(TAG_ROUNDS, "0"))

    @property
    def planned_rounds(self) -> int | None:
        """Rounds the trial has in all (None: not recorded)."""
        value = self.tags.get(TAG_PLANNED_ROUNDS, "")
        return int(value) if value.isdigit() else None

    @property
    def round_work(self) -> list[float] | None:
        """Each round's expected wall time relative to the others (None: not recorded or unreadable)."""
        return decode_round_work(self.tags.get(TAG_ROUND_WORK, ""))

    @property
    def overrides(self) -> dict[str, Any]:
        """The trial's swept values."""
        return {k.removeprefix(TAG_OVERRIDE): json.loads(v) for k, v in self.tags.items() if k.startswith(TAG_OVERRIDE)}

    @property
    def versions(self) -> dict[str, str]:
        """package -> version the trial ran with."""
        return {k.removeprefix(TAG_VERSION): v for k, v in self.tags.items() if k.startswith(TAG_VERSION)}

    @property
    def threads_per_worker(self) -> int | None:
        """The CPUs per unit of work the trial last ran with (None: not recorded)."""
        value = self.tags.get(TAG_THREADS, self.params.get(PARAM_THREADS))
        return int(value) if value is not None and value.isdigit() else None

    @property
    def machine(self) -> dict[str, str]:
        """The worker the trial ran on: cpu_model, cpus, host."""
        return {k.removeprefix(TAG_MACHINE): v for k, v in self.tags.items() if k.startswith(TAG_MACHINE)}

    @property
    def code(self) -> str:
        """The commit that ran (with a note on uncommitted changes), else the package version."""
        commit = self.tags.get(TAG_COMMIT)
        if commit is None:
            return self.tags.get(TAG_CODE_VERSION, "?")
        return commit + (" (uncommitted changes)" if self.tags.get(TAG_DIRTY) == "true" else "")


class StoredCheckpoint(NamedTuple):
    """A verified checkpoint read back from a run."""

    round_index: int
    """The last round the checkpoint includes."""
    data: bytes
    """The checkpoint file (see workers.checkpoint)."""


class Tracker:
    """MLflow access for the service (driver side)."""

    def __init__(self, tracking_uri: str | None = None):
        """Open the store (creating an embedded one that does not exist); :class:`StoreUnavailable` if it cannot be
        used."""
        self.uri = resolve_tracking_uri(tracking_uri)
        problem = store_problem(self.uri)
        if problem:
            raise StoreUnavailable(f"cannot use the MLflow store {self.uri}: {problem}")
        try:
            database = sqlite_path(self.uri)
            self.client = (
                MlflowClient(tracking_uri=self.uri) if database is None else self._open_sqlite_store(self.uri, database)
            )
        except Exception as error:  # noqa: BLE001 - MLflow's and its database drivers' errors alike
            reason = next((line for line in str(error).splitlines() if line.strip()), type(error).__name__)
            raise StoreUnavailable(f"cannot use the MLflow store {self.uri}: {reason[:300]}") from error

    @staticmethod
    def _open_sqlite_store(uri: str, database: Path) -> MlflowClient:
        """A client of the embedded store, which it creates (or migrates) under a file lock.

        MLflow creates its tables when the client is constructed and on first use; two processes doing that at
        once (``icemlab status`` while ``icemlab run`` starts on a fresh store, a test polling a driver's store)
        make one of them fail with "table ... already exists".
        """
        import fcntl

        database.parent.mkdir(parents=True, exist_ok=True)
        with open(database.with_name(database.name + ".lock"), "w") as lock:
            fcntl.flock(lock, fcntl.LOCK_EX)
            try:
                client = MlflowClient(tracking_uri=uri)
                client.search_experiments(max_results=1)
            finally:
                fcntl.flock(lock, fcntl.LOCK_UN)
        return client

    # ------------------------------------------------------------ sweeps
    def experiment_id(self, name: str, create: bool = True) -> str | None:
        experiment = self.client.get_experiment_by_name(name)
        if experiment is not None:
            if experiment.lifecycle_stage == "deleted":
                self.client.restore_experiment(experiment.experiment_id)
            return experiment.experiment_id
        if not create:
            return None
        artifact_location = None
        if self.uri.startswith("sqlite:"):
            # Artifacts beside the database, wherever the command was run from.
            database = sqlite_path(self.uri)
            artifact_location = (database.parent / "mlruns").resolve().as_uri()
        experiment_id = self.client.create_experiment(name, artifact_location=artifact_location)
        # Show it as a model-training experiment (runs, metrics), not a GenAI one, in MLflow 3's UI.
        self.client.set_experiment_tag(experiment_id, "mlflow.experimentKind", "custom_model_development")
        return experiment_id

    @staticmethod
    def _sweep_record(run) -> SweepRun:
        return SweepRun(
            run.info.run_id,
            run.data.tags.get(TAG_SWEEP, "?"),
            run.info.status,
            run.info.experiment_id,
            dict(run.data.tags),
            dict(run.data.metrics),
        )

    def find_sweep_run(self, experiment: str, sweep_name: str) -> SweepRun | None:
        """The latest parent run of a sweep, or None."""
        experiment_id = self.experiment_id(experiment, create=False)
        if experiment_id is None:
            return None
        runs = self.client.search_runs(
            [experiment_id],
            filter_string=f"tags.`{TAG_KIND}` = 'sweep' and tags.`{TAG_SWEEP}` = '{sweep_name}'",
            order_by=["attributes.start_time DESC"],
            max_results=1,
        )
        return self._sweep_record(runs[0]) if runs else None

    def start_sweep(
        self,
        experiment: str,
        sweep_name: str,
        file_hash: str,
        yaml_text: str | None,
        tags: dict[str, str],
        version: str,
        planned_trials: int | None = None,
    ) -> str:
        """Create the parent run of a sweep execution; returns its id. The sweep file is logged with it, or, when
        ``yaml_text`` is None, by :meth:`record_sweep_file` once the caller holds the id (so that a store failing,
        or a Ctrl-C, in between finds a run it can close)."""
        if planned_trials is not None:
            tags = {**tags, TAG_PLANNED_TRIALS: str(planned_trials)}
        experiment_id = self.experiment_id(experiment)
        run = self.client.create_run(
            experiment_id,
            run_name=f"{sweep_name}",
            tags={
                TAG_KIND: "sweep",
                TAG_SWEEP: sweep_name,
                TAG_SWEEP_HASH: file_hash,
                TAG_SESSION_STARTED: f"{time.time():.3f}",
                TAG_DRIVER: this_driver(),
                "icemlab.version": version,
                **tags,
            },
        )
        if yaml_text is not None:
            self.record_sweep_file(run.info.run_id, yaml_text)
        return run.info.run_id

    def record_sweep_file(self, run_id: str, yaml_text: str) -> None:
        """The sweep file a sweep's run runs (what `icemlab report NAME` plans from)."""
        self.client.log_text(run_id, yaml_text, "sweep.yaml")

    def reopen_sweep(self, run_id: str, file_hash: str, planned_trials: int, yaml_text: str | None = None) -> None:
        """Mark a parent run RUNNING again for a resume; an earlier session's driver error is history. A sweep
        file edited since (``yaml_text``) becomes the run's sweep.yaml, what `icemlab report NAME` plans from;
        the one it replaces is kept under sweep_history/."""
        if yaml_text is not None:
            recorded = self.recorded_sweep(run_id)
            if recorded is not None and recorded != yaml_text:
                self.client.log_text(run_id, recorded, f"sweep_history/sweep_{_now_ms()}.yaml")
            if recorded != yaml_text:
                self.record_sweep_file(run_id, yaml_text)
        self.client.update_run(run_id, status=RUNNING)
        tags = self.client.get_run(run_id).data.tags
        for tag in (TAG_ERROR, TAG_ERROR_CLASS, TAG_INTERRUPTED):  # this session ends with its own
            if tag in tags:
                self.client.delete_tag(run_id, tag)
        self.client.set_tag(run_id, "icemlab.resumed_with_hash", file_hash)
        self.client.set_tag(run_id, TAG_PLANNED_TRIALS, str(planned_trials))
        self.client.set_tag(run_id, TAG_SESSION_STARTED, f"{time.time():.3f}")
        self.client.set_tag(run_id, TAG_DRIVER, this_driver())

    def end_sweep(
        self,
        run_id: str,
        status: str,
        summary: dict[str, float],
        failed_trials: int | None = None,
        artifacts: Iterable[Path] = (),
        interrupted: bool = False,
    ) -> None:
        now = _now_ms()
        tags = {}
        if failed_trials is not None:
            tags[TAG_FAILED_TRIALS] = str(failed_trials)
        if interrupted:
            tags[TAG_INTERRUPTED] = "true"
        self.client.log_batch(
            run_id,
            metrics=[Metric(k, float(v), now, 0) for k, v in summary.items()],
            tags=[RunTag(k, v) for k, v in tags.items()],
        )
        for path in artifacts:
            self.client.log_artifact(run_id, str(path))
        self.client.set_terminated(run_id, status=status)

    def past_costs(self, tags: Mapping[str, str], limit: int = 20) -> list[float]:
        """Core-seconds per unit of work of the newest finished trials whose tags match (for sweep plans)."""
        experiments = [e.experiment_id for e in self.client.search_experiments()]
        if not experiments:
            return []
        conditions = [f"tags.`{key}` = '{value}'" for key, value in tags.items()]
        conditions += ["attributes.status = 'FINISHED'", f"metrics.`{CORE_SECONDS_PER_WORK}` > 0"]
        runs = self.client.search_runs(experiments, " and ".join(conditions), max_results=limit,
                                       order_by=["attributes.start_time DESC"])  # fmt: skip
        return [run.data.metrics[CORE_SECONDS_PER_WORK] for run in runs]

    def sweeps(self) -> list[SweepRun]:
        """Every sweep parent run, newest first."""
        experiments = self.client.search_experiments()
        if not experiments:
            return []
        runs = self.client.search_runs(
            [e.experiment_id for e in experiments],
            filter_string=f"tags.`{TAG_KIND}` = 'sweep'",
            order_by=["attributes.start_time DESC"],
            max_results=1000,
        )
        return [self._sweep_record(run) for run in runs]

    # ------------------------------------------------------------ trials
    def trial_runs(self, parent_run_id: str) -> list[TrialRun]:
        """Every child run of a parent run."""
        parent = self.client.get_run(parent_run_id)
        runs = self.client.search_runs(
            [parent.info.experiment_id],
            filter_string=f"tags.`{TAG_PARENT}` = '{parent_run_id}'",
            max_results=50000,
        )
        return [self._trial_record(run) for run in runs]

    def trial_run(self, run_id: str) -> TrialRun | None:
        """One trial's run by id, or None if the store has no such trial run."""
        try:
            run = self.client.get_run(run_id)
        except MlflowException:
            return None
        if run.data.tags.get(TAG_KIND) != "trial":
            return None
        return self._trial_record(run)

    @staticmethod
    def _trial_record(run) -> TrialRun:
        return TrialRun(
            run.info.run_id,
            run.data.tags.get(TAG_TRIAL_KEY, ""),
            run.info.status,
            run.data.tags.get(TAG_RUN_NAME, ""),
            dict(run.data.params),
            dict(run.data.tags),
            dict(run.data.metrics),
            run.info.end_time / 1000 if run.info.end_time else None,
        )

    def start_trial(
        self,
        parent_run_id: str,
        trial_key: str,
        name: str,
        params: dict[str, Any],
        tags: dict[str, str],
        artifacts: Mapping[str, str] = {},
        variant: str | None = None,
        overrides: Mapping[str, Any] = {},
    ) -> str:
        """Create a trial's child run with its params, tags, variant and swept values, and text artifacts."""
        parent = self.client.get_run(parent_run_id)
        tags = {TAG_PARENT: parent_run_id, TAG_KIND: "trial", TAG_TRIAL_KEY: trial_key, TAG_ATTEMPTS: "1", **tags}
        if variant:
            tags[TAG_VARIANT] = variant
        tags |= {TAG_OVERRIDE + key: json.dumps(value) for key, value in overrides.items()}
        run = self.client.create_run(parent.info.experiment_id, run_name=name, tags=tags)
        self._record_trial(run.info.run_id, params, artifacts)
        return run.info.run_id

    def _record_trial(self, run_id: str, params: Mapping[str, Any], artifacts: Mapping[str, str]) -> None:
        params_list = [Param(k, _param(v)) for k, v in params.items()]
        for start in range(0, len(params_list), 100):
            self.client.log_batch(run_id, params=params_list[start : start + 100])
        for path, text in artifacts.items():
            self.client.log_text(run_id, text, path)

    def reopen_trial(
        self, run_id: str, attempt: int, params: Mapping[str, Any] = {}, artifacts: Mapping[str, str] = {}
    ) -> None:
        """Continue a trial's run for another attempt (after a failure, a lost process or a resume), first
        recording those of ``params`` and ``artifacts`` it lacks (a driver may have died while it created the
        run; a recorded param keeps its value)."""
        run = self.client.get_run(run_id)
        present = set(self.list_files(run_id)) if artifacts else set()
        self._record_trial(
            run_id,
            {k: v for k, v in params.items() if k not in run.data.params},
            {path: text for path, text in artifacts.items() if path not in present},
        )
        self.client.set_tag(run_id, TAG_ATTEMPTS, str(attempt))
        if run.info.status != RUNNING:
            self.client.update_run(run_id, status=RUNNING)

    def set_tags(self, run_id: str, tags: Mapping[str, str]) -> None:
        self.client.log_batch(run_id, tags=[RunTag(k, str(v)[:MAX_TAG_LENGTH]) for k, v in tags.items()])

    def record_provenance(self, run_id: str, provenance) -> None:
        """The code (version, commit, uncommitted changes) and package versions that run the trial now."""
        tags = {TAG_CODE_VERSION: provenance.version}
        if provenance.commit is not None:
            tags |= {TAG_COMMIT: provenance.commit, TAG_DIRTY: str(bool(provenance.dirty)).lower()}
        tags |= {TAG_VERSION + name: value for name, value in provenance.packages.items()}
        self.set_tags(run_id, tags)

    def record_machine(self, run_id: str, machine: Mapping[str, str]) -> None:
        """The worker that runs the trial (cpu_model, cpus, host)."""
        self.set_tags(run_id, {TAG_MACHINE + key: value for key, value in machine.items()})

    def logged_rounds(self, run_id: str) -> set[int]:
        """Rounds whose metrics are in the run (their marker was logged)."""
        return {m.step for m in self.client.get_metric_history(run_id, ROUND_MARKER)}

    def log_round(
        self,
        run_id: str,
        index: int,
        step: int,
        metrics: Mapping[str, float],
        series: Mapping[str, Sequence[float]],
        series_start: int,
        artifacts: Sequence[tuple[str, bytes]] = (),
        seconds: float | None = None,
        after_a_crash: bool = False,
    ) -> None:
        """Log one round: per-step series, round metrics at ``step``, files; the round marker last.

        Args:
            after_a_crash: the round may have been logged in part before its attempt ended (a round of more
                than MAX_BATCH entries is written in several batches, the marker in the last): the (metric,
                step) entries already written are not written again.
        """
        now = _now_ms()
        entries = [
            Metric(key, float(value), now, series_start + t)
            for key, values in series.items()
            for t, value in enumerate(values)
        ]
        entries += [Metric(key, float(value), now, step) for key, value in metrics.items()]
        if artifacts:
            with tempfile.TemporaryDirectory() as directory:
                for path, data in artifacts:
                    local = Path(directory) / path
                    local.parent.mkdir(parents=True, exist_ok=True)
                    local.write_bytes(data)
                    self.client.log_artifact(run_id, str(local), str(Path(path).parent) if "/" in path else None)
        if seconds is not None:
            entries.append(Metric(ROUND_SECONDS, float(seconds), now, index))
        if after_a_crash:
            keys = {entry.key for entry in entries}
            written = {(key, m.step) for key in keys for m in self.client.get_metric_history(run_id, key)}
            entries = [entry for entry in entries if (entry.key, entry.step) not in written]
        # The marker goes into the last batch: a round counts as logged only once all of it is.
        entries.append(Metric(ROUND_MARKER, float(index), now, index))
        for start in range(0, len(entries), MAX_BATCH):
            self.client.log_batch(run_id, metrics=entries[start : start + MAX_BATCH])
        self.client.set_tag(run_id, TAG_ROUNDS, str(index + 1))

    def record_failure(self, run_id: str, attempt: int, kind: str, cause: str, detail: str) -> None:
        """Say in the run why an attempt ended: its class, a one-line cause, the full text as a file."""
        self.client.log_batch(
            run_id,
            tags=[RunTag(TAG_ERROR, cause[-MAX_TAG_LENGTH:]), RunTag(TAG_ERROR_CLASS, kind)],
            metrics=[Metric(f"failures/{kind}", 1.0, _now_ms(), attempt)],
        )
        self.client.log_text(
            run_id, f"class: {kind}\ncause: {cause}\n\n{detail}", f"failures/attempt_{attempt:03d}_{kind}.txt"
        )

    def record_recovery(self, run_id: str, number: int, kind: str, cause: str) -> None:
        """Say in the run that a worker was lost and recovered inside an attempt (the trial went on).

        ``number`` counts the trial's recoveries (the metric's step); the run's status and error tags stay.
        """
        self.client.log_batch(run_id, metrics=[Metric(f"recovered/{kind}", 1.0, _now_ms(), number)])
        self.client.log_text(run_id, f"class: {kind}\ncause: {cause}\n", f"failures/recovery_{number:03d}_{kind}.txt")

    def record_sweep_failure(self, run_id: str, kind: str, cause: str, detail: str) -> None:
        """:meth:`record_failure` for a sweep's run, numbered after the failures it already records: a driver error
        of a resumed session is kept beside the earlier sessions' ones."""
        self.record_failure(run_id, self._failure_files(run_id, "attempt_") + 1, kind, cause, detail)

    def recoveries(self, run_id: str) -> int:
        """How many in-place recoveries a trial's run records (the next one is numbered after them): its files, or
        its metric's last step where a driver died between writing the metric and the file."""
        keys = [key for key in self.client.get_run(run_id).data.metrics if key.startswith("recovered/")]
        steps = [step for key in keys for step, _ in self.metric_history(run_id, key)]
        return max([self._failure_files(run_id, "recovery_"), *steps])

    def _failure_files(self, run_id: str, prefix: str) -> int:
        return sum(1 for path in self.list_files(run_id, "failures") if path.rsplit("/", 1)[-1].startswith(prefix))

    def record_summary(self, run_id: str, summary: Mapping[str, float], last_round: int | None = None) -> None:
        """A trial's summary metrics, written once: a second call (a resume that ran the last round again) keeps
        the first.

        Args:
            last_round: the round that ended the trial, kept in the tag (:meth:`summarised_round`).
        """
        if TAG_SUMMARY in self.client.get_run(run_id).data.tags:
            return
        now = _now_ms()
        metrics = [Metric(k, float(v), now, 0) for k, v in summary.items()]
        value = "1" if last_round is None else f"round {last_round}"
        # One batch with its tag: a driver killed while it is sent leaves either all of it or none.
        self.client.log_batch(run_id, metrics=metrics, tags=[RunTag(TAG_SUMMARY, value)])

    def summarised_round(self, run_id: str) -> int | None:
        """The round whose end the trial's summary was written at; None without a summary, or one written before
        the tag named its round."""
        value = self.client.get_run(run_id).data.tags.get(TAG_SUMMARY, "")
        return int(value.split()[1]) if value.startswith("round ") else None

    def end_trial(self, run_id: str, status: str, summary: Mapping[str, float] | None = None) -> None:
        """Close a trial's run: FINISHED with its summary metrics (once, also when a driver died while it closed
        the run), or FAILED / KILLED."""
        if summary:
            self.record_summary(run_id, summary)
        if status == FINISHED:
            tags = self.client.get_run(run_id).data.tags
            # Earlier attempts' errors stay in failures/; the tags describe why a run is not FINISHED.
            for tag in (TAG_ERROR, TAG_ERROR_CLASS):
                if tag in tags:
                    self.client.delete_tag(run_id, tag)
        self.client.set_terminated(run_id, status=status)

    def metric_history(self, run_id: str, key: str) -> list[tuple[int, float]]:
        """(step, value) by step; a step logged twice (a round re-run after a crash) keeps its entries in the order
        they were logged, so that a dict of the pairs holds the latest."""
        entries = sorted(self.client.get_metric_history(run_id, key), key=lambda m: (m.step, m.timestamp))
        return [(m.step, m.value) for m in entries]

    def histories(self, run_ids: Iterable[str], keys: Iterable[str]) -> dict[str, dict[str, list[tuple[int, float]]]]:
        """Metric histories of several runs, for curve plots."""
        keys = list(keys)
        return {run_id: {key: self.metric_history(run_id, key) for key in keys} for run_id in run_ids}

    def list_files(self, run_id: str, path: str | None = None) -> list[str]:
        """Artifact paths of a run (one level)."""
        return [f.path for f in self.client.list_artifacts(run_id, path)]

    def download(self, run_id: str, path: str, directory: str | Path) -> Path:
        return Path(self.client.download_artifacts(run_id, path, str(directory)))

    def recorded_sweep(self, run_id: str) -> str | None:
        """The sweep file a sweep's run recorded when it started (None if it has none)."""
        with tempfile.TemporaryDirectory() as directory:
            try:
                return self.download(run_id, "sweep.yaml", directory).read_text()
            except (OSError, MlflowException):
                return None

    # -------------------------------------------------------- checkpoints
    def save_checkpoint(self, run_id: str, round_index: int, data: bytes) -> None:
        """Write a checkpoint after round ``round_index``: state first, manifest last; keep the newest few."""
        folder = f"{CHECKPOINTS}/round_{round_index:06d}"
        manifest = {"round": round_index, "bytes": len(data), "sha256": digest(data), "written": _now_ms()}
        with tempfile.TemporaryDirectory() as directory:
            state = Path(directory) / "state.npz"
            state.write_bytes(data)
            self.client.log_artifact(run_id, str(state), folder)
            (Path(directory) / "manifest.json").write_text(json.dumps(manifest))
            self.client.log_artifact(run_id, str(Path(directory) / "manifest.json"), folder)
        self._prune_checkpoints(run_id, round_index)

    def _checkpoint_rounds(self, run_id: str) -> list[int]:
        rounds = []
        for path in self.list_files(run_id, CHECKPOINTS):
            name = path.rsplit("/", 1)[-1]
            if name.startswith("round_") and name[6:].isdigit():
                rounds.append(int(name[6:]))
        return sorted(rounds)

    def _prune_checkpoints(self, run_id: str, written: int) -> None:
        """Keep the newest few checkpoints up to the one just ``written``. Later ones are left alone and not
        counted: they exist only when the trial went back past them (they were refused), and counting them
        would delete the one just written."""
        rounds = [r for r in self._checkpoint_rounds(run_id) if r <= written]
        if len(rounds) <= KEEP_CHECKPOINTS:
            return
        try:
            from mlflow.store.artifact.artifact_repository_registry import get_artifact_repository

            repository = get_artifact_repository(self.client.get_run(run_id).info.artifact_uri)
            for old in rounds[:-KEEP_CHECKPOINTS]:
                repository.delete_artifacts(f"{CHECKPOINTS}/round_{old:06d}")
        except (MlflowException, NotImplementedError, OSError) as error:  # a store that cannot delete keeps them
            logging.getLogger(__name__).info("old checkpoints kept: %s", error)

    def load_checkpoint(self, run_id: str, skip: Iterable[int] = ()) -> tuple[StoredCheckpoint | None, list[str]]:
        """The newest checkpoint whose state matches its manifest, and a note per checkpoint passed over.

        Args:
            skip: rounds whose checkpoints were found unusable before (e.g. refused by the program).
        """
        notes: list[str] = []
        skipped = set(skip)
        for round_index in reversed(self._checkpoint_rounds(run_id)):
            if round_index in skipped:
                continue
            folder = f"{CHECKPOINTS}/round_{round_index:06d}"
            with tempfile.TemporaryDirectory() as directory:
                try:
                    manifest = json.loads(self.download(run_id, f"{folder}/manifest.json", directory).read_text())
                    data = self.download(run_id, f"{folder}/state.npz", directory).read_bytes()
                except (MlflowException, OSError, ValueError) as error:
                    notes.append(f"checkpoint of round {round_index} is incomplete ({type(error).__name__}); skipped")
                    continue
            if len(data) != manifest.get("bytes") or digest(data) != manifest.get("sha256"):
                notes.append(
                    f"checkpoint of round {round_index} does not match its manifest "
                    f"({len(data)} bytes, expected {manifest.get('bytes')}; checksum differs); skipped"
                )
                continue
            return StoredCheckpoint(round_index, data), notes
        return None, notes

    def note(self, run_id: str, text: str) -> None:
        """Append a line to the run's notes file (checkpoints skipped, resumes)."""
        # The counter keeps two notes of one millisecond apart; file names still sort by time.
        self.client.log_text(run_id, text + "\n", f"notes/{_now_ms()}_{next(_NOTE_NUMBERS):06d}.txt")


def _param(value: Any) -> str:
    if value is None:
        return "None"
    if isinstance(value, (dict, list)):
        return json.dumps(value, sort_keys=True)
    return str(value)


def _now_ms() -> int:
    return int(time.time() * 1000)


_NOTE_NUMBERS = itertools.count()
"""Numbers this process's notes (see :meth:`Tracker.note`)."""


__all__ = [
    "FAILED",
    "FINISHED",
    "KILLED",
    "RUNNING",
    "StoredCheckpoint",
    "SweepRun",
    "Tracker",
    "TrialRun",
    "resolve_tracking_uri",
]
