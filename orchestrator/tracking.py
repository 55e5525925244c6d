"""Everything that talks to MLflow (the only module that imports mlflow).

Run tree: one experiment per sweep; a parent run per sweep execution (the YAML,
summary table and plots); a child run per trial attempt (resolved config as
params; trial_key / task / algorithm / seed tags; per-step and per-episode
metrics; episode plots). Only the driver writes, so the embedded SQLite store
sees exactly one writer.

Identity and resume: a trial is its key (hash of resolved config and seed).
A key with a FINISHED child run is never run or logged again. An attempt that
did not finish (driver killed, trial raised) keeps its run with status KILLED
or FAILED and the tag ``icemlab.superseded_by`` pointing at the next attempt,
so each trial ends with exactly one current run.
"""

from __future__ import annotations

import logging
import os
import time
from collections.abc import Iterable
from pathlib import Path
from typing import Any, NamedTuple

# Keep MLflow quiet and local: no telemetry, no background job runner.
os.environ.setdefault("MLFLOW_DISABLE_TELEMETRY", "true")
os.environ.setdefault("DO_NOT_TRACK", "true")

from mlflow.entities import Metric, Param, RunStatus, RunTag  # noqa: E402
from mlflow.tracking import MlflowClient  # noqa: E402

# Database set-up messages are not news to the user.
logging.getLogger("mlflow.store.db.utils").setLevel(logging.WARNING)
logging.getLogger("alembic").setLevel(logging.WARNING)

TAG_KIND = "icemlab.kind"
TAG_SWEEP = "icemlab.sweep"
TAG_SWEEP_HASH = "icemlab.sweep_file_hash"
TAG_TRIAL_KEY = "icemlab.trial_key"
TAG_ATTEMPT = "icemlab.attempt"
TAG_SUPERSEDED = "icemlab.superseded_by"
TAG_ERROR = "icemlab.error"
TAG_PARENT = "mlflow.parentRunId"
MAX_BATCH = 1000  # MLflow's limit of metrics per log_batch request
MAX_TAG_LENGTH = 5000


def default_tracking_uri(directory: Path | None = None) -> str:
    """The embedded store: SQLite in the working directory, no server needed."""
    directory = Path.cwd() if directory is None else directory
    return f"sqlite:///{(directory / 'mlflow.db').resolve()}"


def resolve_tracking_uri(uri: str | None) -> str:
    """Explicit URI, else MLFLOW_TRACKING_URI, else the embedded SQLite store."""
    return uri or os.environ.get("MLFLOW_TRACKING_URI") or default_tracking_uri()


class TrialRun(NamedTuple):
    """A child run of a sweep, as found in MLflow."""

    run_id: str
    trial_key: str
    status: str
    superseded: bool
    params: dict[str, str]
    tags: dict[str, str]
    metrics: dict[str, float]


class Tracker:
    """MLflow access for the service (driver side)."""

    def __init__(self, tracking_uri: str | None = None):
        self.uri = resolve_tracking_uri(tracking_uri)
        self.client = MlflowClient(tracking_uri=self.uri)
        self._local_artifacts = self.uri.startswith("sqlite:") or "://" not in self.uri

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
            database = Path(self.uri.removeprefix("sqlite:///"))
            artifact_location = (database.parent / "mlruns").resolve().as_uri()
        experiment_id = self.client.create_experiment(name, artifact_location=artifact_location)
        # Show it as a model-training experiment (runs, metrics), not a GenAI one, in MLflow 3's UI.
        self.client.set_experiment_tag(experiment_id, "mlflow.experimentKind", "custom_model_development")
        return experiment_id

    def find_sweep_run(self, experiment: str, sweep_name: str) -> Any | None:
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
        return runs[0] if runs else None

    def start_sweep(
        self, experiment: str, sweep_name: str, file_hash: str, yaml_text: str, tags: dict[str, str], version: str
    ) -> str:
        """Create the parent run of a sweep execution; returns its id."""
        experiment_id = self.experiment_id(experiment)
        run = self.client.create_run(
            experiment_id,
            run_name=f"{sweep_name}",
            tags={
                TAG_KIND: "sweep",
                TAG_SWEEP: sweep_name,
                TAG_SWEEP_HASH: file_hash,
                "icemlab.version": version,
                **tags,
            },
        )
        self.client.log_text(run.info.run_id, yaml_text, "sweep.yaml")
        return run.info.run_id

    def reopen_sweep(self, run_id: str, file_hash: str) -> None:
        """Mark a parent run RUNNING again for a resume."""
        self.client.update_run(run_id, status="RUNNING")
        self.client.set_tag(run_id, "icemlab.resumed_with_hash", file_hash)

    def end_sweep(
        self, run_id: str, status: str, summary: dict[str, float], tags: dict[str, str], artifacts: Iterable[Path] = ()
    ) -> None:
        now = _now_ms()
        self.client.log_batch(
            run_id,
            metrics=[Metric(k, float(v), now, 0) for k, v in summary.items()],
            tags=[RunTag(k, v) for k, v in tags.items()],
        )
        for path in artifacts:
            self.client.log_artifact(run_id, str(path))
        self.client.set_terminated(run_id, status=status)

    # ------------------------------------------------------------ trials
    def trial_runs(self, parent_run_id: str) -> list[TrialRun]:
        """Every child run of a parent run (all attempts)."""
        parent = self.client.get_run(parent_run_id)
        runs = self.client.search_runs(
            [parent.info.experiment_id],
            filter_string=f"tags.`{TAG_PARENT}` = '{parent_run_id}'",
            max_results=50000,
        )
        return [
            TrialRun(
                run.info.run_id,
                run.data.tags.get(TAG_TRIAL_KEY, ""),
                run.info.status,
                TAG_SUPERSEDED in run.data.tags,
                run.data.params,
                run.data.tags,
                run.data.metrics,
            )
            for run in runs
        ]

    def start_trial(
        self, parent_run_id: str, trial_key: str, name: str, params: dict[str, Any], tags: dict[str, str], attempt: int
    ) -> str:
        parent = self.client.get_run(parent_run_id)
        run = self.client.create_run(
            parent.info.experiment_id,
            run_name=name,
            tags={
                TAG_PARENT: parent_run_id,
                TAG_KIND: "trial",
                TAG_TRIAL_KEY: trial_key,
                TAG_ATTEMPT: str(attempt),
                **tags,
            },
        )
        self.client.log_batch(run.info.run_id, params=[Param(k, _param(v)) for k, v in params.items()])
        return run.info.run_id

    def supersede(self, run_id: str, by_run_id: str, status: str) -> None:
        """Close an earlier attempt (KILLED or FAILED) and point it at the next one."""
        self.client.set_tag(run_id, TAG_SUPERSEDED, by_run_id)
        if self.client.get_run(run_id).info.status in ("RUNNING", "SCHEDULED"):
            self.client.set_terminated(run_id, status=status)

    def log_episode(
        self,
        run_id: str,
        episode: int,
        step_offset: int,
        per_step: dict[str, Iterable[float]],
        per_episode: dict[str, float],
    ) -> None:
        """Log one episode: per-step series (steps counted across episodes) and per-episode figures."""
        now = _now_ms()
        metrics = [
            Metric(key, float(value), now, step_offset + t)
            for key, values in per_step.items()
            for t, value in enumerate(values)
        ]
        metrics += [Metric(key, float(value), now, episode) for key, value in per_episode.items()]
        for start in range(0, len(metrics), MAX_BATCH):
            self.client.log_batch(run_id, metrics=metrics[start : start + MAX_BATCH])

    def log_figure(self, run_id: str, figure: Any, artifact_file: str) -> None:
        self.client.log_figure(run_id, figure, artifact_file)

    def log_text(self, run_id: str, text: str, artifact_file: str) -> None:
        self.client.log_text(run_id, text, artifact_file)

    def end_trial(
        self, run_id: str, status: str, summary: dict[str, float] | None = None, error: str | None = None
    ) -> None:
        """Close a trial run: FINISHED with summary metrics, or FAILED / KILLED with the error."""
        if summary:
            now = _now_ms()
            self.client.log_batch(run_id, metrics=[Metric(k, float(v), now, 0) for k, v in summary.items()])
        if error:
            self.client.set_tag(run_id, TAG_ERROR, error[-MAX_TAG_LENGTH:])
            self.client.log_text(run_id, error, "error.txt")
        self.client.set_terminated(run_id, status=status)

    def metric_history(self, run_id: str, key: str) -> list[tuple[int, float]]:
        return [(m.step, m.value) for m in self.client.get_metric_history(run_id, key)]

    # ------------------------------------------------------------ lookup
    def sweeps(self) -> list[Any]:
        """Every sweep parent run, newest first."""
        experiments = self.client.search_experiments()
        if not experiments:
            return []
        return self.client.search_runs(
            [e.experiment_id for e in experiments],
            filter_string=f"tags.`{TAG_KIND}` = 'sweep'",
            order_by=["attributes.start_time DESC"],
            max_results=1000,
        )


def _param(value: Any) -> str:
    return "None" if value is None else str(value)


def _now_ms() -> int:
    return int(time.time() * 1000)


FINISHED = RunStatus.to_string(RunStatus.FINISHED)
FAILED = RunStatus.to_string(RunStatus.FAILED)
KILLED = RunStatus.to_string(RunStatus.KILLED)
RUNNING = RunStatus.to_string(RunStatus.RUNNING)
__all__ = ["FAILED", "FINISHED", "KILLED", "RUNNING", "Tracker", "TrialRun", "resolve_tracking_uri"]
