"""The Ray driver: places trials and their simulation workers, bounded concurrency, retries.

``ray.init()`` starts a local single-node Ray by default; an address connects
to an existing cluster. Every trial runs in a TrialRunner actor whose MPC loop
takes its trajectory-batch costs from a SimulationPool (a co-located
SimulationWorker plus ``simulation_workers - 1`` SimulationWorker actors).
The driver is the only process that writes to MLflow: runners send each
finished episode back and the driver logs it.

Faults: a SimulationWorker actor that dies is restarted by Ray and its call
retried (the call is a pure function of state and actions), so the episode
completes and the restart is counted in the trial's metrics. A trial that
raises (or whose runner dies) ends its attempt FAILED with the error in the
run and is retried up to ``retries`` times; the sweep goes on. Ctrl-C kills
the running trials and marks their runs, and the sweep's, KILLED.
"""

from __future__ import annotations

import logging
import os
import time
import traceback
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, NamedTuple

import numpy as np

from orchestrator import report
from orchestrator.interrupt import InterruptRequest
from orchestrator.pool import SimulationPool
from orchestrator.sweep import LoadedSweep, Trial
from orchestrator.tracking import FAILED, FINISHED, KILLED, Tracker, TrialRun
from workers import code_fingerprint
from workers.actors import EpisodeReport, SimulationWorker, TrialRunner

PROGRESS_POLL_SECONDS = 0.5


def icemlab_version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("icemlab")
    except PackageNotFoundError:
        return "dev"


@dataclass
class ActiveTrial:
    """A trial attempt in flight."""

    trial: Trial
    run_id: str
    attempt: int
    runner: Any
    workers: list[Any]
    episode: int = 0
    episode_ref: Any = None
    progress_ref: Any = None
    progress: dict[str, Any] = field(default_factory=dict)
    started: float = field(default_factory=time.monotonic)
    reports: list[EpisodeReport] = field(default_factory=list)


class SweepState(NamedTuple):
    """What the progress display shows."""

    name: str
    total: int
    done: int
    failed: int
    running: list[tuple[str, int, dict[str, Any]]]
    """(trial label, episodes of the trial, runner progress) per running trial."""
    elapsed: float
    eta: float | None


class SweepOutcome(NamedTuple):
    parent_run_id: str
    finished: int
    failed: int
    skipped: int
    """Trials already FINISHED in MLflow before this run (resume)."""
    table: str


def trial_label(trial: Trial) -> str:
    planner = trial.config.planner
    return f"{trial.config.task}/{planner.algorithm}/b{planner.budget}/s{trial.config.seed}"


def connect_ray(address: str | None, num_cpus: int | None = None) -> bool:
    """Connect to a cluster at ``address`` or start a local one; True if this call started Ray."""
    import ray

    if ray.is_initialized():
        return False
    os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
    common = dict(include_dashboard=False, log_to_driver=False, logging_level=logging.ERROR)
    if address:
        try:
            ray.init(address=address, **common)
        except ConnectionError as error:
            raise ConnectionError(
                f"cannot connect to the Ray cluster at {address} ({error}). Check the address (ray://HOST:10001 "
                "for Ray Client, HOST:6379 for the GCS); if the cluster uses token authentication, set "
                "RAY_AUTH_MODE=token and provide the token (RAY_AUTH_TOKEN or ~/.ray/auth_token)."
            ) from None
    else:
        ray.init(num_cpus=num_cpus or os.cpu_count(), **common)
    return True


class SweepScheduler:
    """Runs the pending trials of a loaded sweep on Ray and records them through a Tracker."""

    def __init__(
        self,
        loaded: LoadedSweep,
        tracker: Tracker,
        *,
        address: str | None = None,
        resume: bool = False,
        max_concurrent: int | None = None,
        display: Callable[[SweepState], None] | None = None,
        runner_class: type = TrialRunner,
    ):
        self.loaded = loaded
        self.sweep = loaded.sweep
        self.tracker = tracker
        self.address = address
        self.resume = resume
        self.max_concurrent = max_concurrent
        self.display = display
        self.runner_class = runner_class
        self.experiment = self.sweep.tracking.experiment or self.sweep.name

    # -------------------------------------------------------------- plan
    def _parent_run(self) -> tuple[str, list[TrialRun]]:
        if self.resume:
            previous = self.tracker.find_sweep_run(self.experiment, self.sweep.name)
            if previous is not None:
                run_id = previous.info.run_id
                self.tracker.reopen_sweep(run_id, self.loaded.file_hash)
                return run_id, self.tracker.trial_runs(run_id)
        run_id = self.tracker.start_sweep(
            self.experiment,
            self.sweep.name,
            self.loaded.file_hash,
            self.loaded.text,
            self.sweep.tracking.tags,
            icemlab_version(),
        )
        return run_id, []

    def _layout(self, cpus: float, pending: int) -> tuple[int, int]:
        """(threads per worker, concurrent trials) for the cluster's CPUs."""
        workers = self.sweep.resources.simulation_workers
        threads = self.sweep.resources.threads_per_worker
        if threads is None:
            # Enough trials to use every CPU once, the rest of the CPUs as threads.
            concurrent = max(1, min(pending, int(cpus) // workers))
            if self.max_concurrent:
                concurrent = min(concurrent, self.max_concurrent)
            threads = max(1, int(cpus) // (concurrent * workers))
        concurrent = max(1, int(cpus) // (threads * workers))
        if self.max_concurrent:
            concurrent = min(concurrent, self.max_concurrent)
        return threads, concurrent

    # --------------------------------------------------------------- run
    def run(self) -> SweepOutcome:
        import ray

        started_ray = connect_ray(self.address)  # before any MLflow run exists: a bad address leaves no trace
        parent_id = None
        try:
            parent_id, previous_runs = self._parent_run()
            finished_keys = {r.trial_key for r in previous_runs if r.status == FINISHED and not r.superseded}
            open_attempts: dict[str, list[TrialRun]] = {}
            attempts_so_far: dict[str, int] = {}
            for run in previous_runs:
                attempts_so_far[run.trial_key] = attempts_so_far.get(run.trial_key, 0) + 1
                if run.trial_key not in finished_keys and not run.superseded:
                    open_attempts.setdefault(run.trial_key, []).append(run)
            pending = [t for t in self.loaded.trials if t.key not in finished_keys]
            skipped = len(self.loaded.trials) - len(pending)
            cpus = ray.cluster_resources().get("CPU", 1)
            threads, concurrent = self._layout(cpus, len(pending))
            with InterruptRequest() as interrupt:
                return self._drive(
                    parent_id, pending, skipped, threads, concurrent, open_attempts, attempts_so_far, interrupt
                )
        except KeyboardInterrupt:
            if parent_id is not None:
                self._abort(parent_id)
            raise
        finally:
            if started_ray:
                ray.shutdown()

    def _drive(self, parent_id, pending, skipped, threads, concurrent, open_attempts, attempts_so_far, interrupt):
        import ray

        queue = list(pending)
        retries_left = {t.key: self.sweep.retries for t in pending}
        self._active: list[ActiveTrial] = []
        self._parent_id = parent_id
        results: list[report.TrialResult] = self._previous_results(parent_id)
        done = failed = 0
        started = time.monotonic()
        last_display = 0.0
        total_steps = sum(self._trial_steps(t) for t in pending)
        finished_steps = 0

        while queue or self._active:
            interrupt.raise_if_requested()
            while queue and len(self._active) < concurrent:
                trial = queue.pop(0)
                attempts_so_far[trial.key] = attempts_so_far.get(trial.key, 0) + 1
                active = self._launch(trial, threads, attempts_so_far[trial.key])
                for stale in open_attempts.pop(trial.key, []):
                    self.tracker.supersede(stale.run_id, active.run_id, KILLED)
                self._active.append(active)

            refs = [a.episode_ref for a in self._active]
            ready, _ = ray.wait(refs, num_returns=1, timeout=PROGRESS_POLL_SECONDS)
            interrupt.raise_if_requested()
            for ref in ready:
                active = next(a for a in self._active if a.episode_ref == ref)
                try:
                    episode = ray.get(ref)
                except Exception as error:  # the trial raised or its runner died
                    self._end_attempt(active)
                    message = _error_text(error)
                    if retries_left[active.trial.key] > 0:
                        retries_left[active.trial.key] -= 1
                        retry = self._launch(active.trial, threads, active.attempt + 1)
                        self.tracker.end_trial(active.run_id, FAILED, error=message)
                        self.tracker.supersede(active.run_id, retry.run_id, FAILED)
                        self._active.append(retry)
                    else:
                        self.tracker.end_trial(active.run_id, FAILED, error=message)
                        total_steps -= self._trial_steps(active.trial)
                        failed += 1
                    continue
                self._record_episode(active, episode)
                if active.episode + 1 < active.trial.config.episodes:
                    active.episode += 1
                    active.episode_ref = active.runner.run_episode.remote(active.episode)
                else:
                    self._end_attempt(active)
                    results.append(self._finish_trial(active))
                    finished_steps += self._trial_steps(active.trial)
                    done += 1

            self._poll_progress()
            now = time.monotonic()
            if self.display is not None and (now - last_display >= PROGRESS_POLL_SECONDS or not self._active):
                last_display = now
                steps_done = finished_steps + sum(self._steps_done(a) for a in self._active)
                rate = steps_done / max(now - started, 1e-9)
                eta = (total_steps - steps_done) / rate if steps_done > 0 else None
                self.display(
                    SweepState(
                        self.sweep.name,
                        len(self.loaded.trials),
                        skipped + done,
                        failed,
                        [(trial_label(a.trial), a.trial.config.episodes, a.progress) for a in self._active],
                        now - started,
                        eta,
                    )
                )

        groups = report.summarize(results)
        table = report.format_table(groups)
        self._end_sweep(parent_id, groups, table, done + skipped, failed)
        return SweepOutcome(parent_id, done, failed, skipped, table)

    # ------------------------------------------------------------ trials
    @staticmethod
    def _trial_steps(trial: Trial) -> int:
        """Environment steps a trial runs (for the ETA)."""
        from workers.tasks import TASKS

        length = trial.config.max_steps or TASKS[trial.config.task].episode_length
        return trial.config.episodes * length

    def _steps_done(self, active: ActiveTrial) -> int:
        finished_episodes = sum(len(r.result.rewards) for r in active.reports)
        in_episode = active.progress.get("step", 0) if active.progress.get("episode") == active.episode else 0
        return finished_episodes + in_episode

    def _launch(self, trial: Trial, threads: int, attempt: int) -> ActiveTrial:
        import ray

        config = trial.config
        remote_count = self.sweep.resources.simulation_workers - 1
        worker_actor = ray.remote(num_cpus=threads, max_restarts=3, max_task_retries=3)(SimulationWorker)
        workers = [worker_actor.remote(config.task, threads, config.task_options) for _ in range(remote_count)]
        pool = SimulationPool(config.task, threads, workers, config.task_options)
        runner_actor = ray.remote(num_cpus=threads, max_concurrency=2, max_restarts=0)(self.runner_class)
        runner = runner_actor.remote(
            config.task,
            config.planner,
            config.seed,
            pool,
            config.max_steps,
            expected_code=code_fingerprint(),
            task_options=config.task_options,
        )
        run_id = self.tracker.start_trial(
            self._parent_id,
            trial.key,
            name=f"{trial_label(trial)}#{trial.key[:6]}",
            params=config.flat()
            | {
                "resources.threads_per_worker": threads,
                "resources.simulation_workers": self.sweep.resources.simulation_workers,
            },
            tags={
                "task": config.task,
                "algorithm": config.planner.algorithm,
                "seed": str(config.seed),
                "budget": str(config.planner.budget),
            },
            attempt=attempt,
        )
        active = ActiveTrial(trial, run_id, attempt, runner, workers)
        active.episode_ref = runner.run_episode.remote(0)
        return active

    def _end_attempt(self, active: ActiveTrial) -> None:
        import ray

        self._active.remove(active)
        for actor in [active.runner, *active.workers]:
            try:
                ray.kill(actor)
            except Exception:  # already gone
                pass

    def _record_episode(self, active: ActiveTrial, episode_report: EpisodeReport) -> None:
        active.reports.append(episode_report)
        episode = episode_report.result
        offset = sum(len(r.result.rewards) for r in active.reports[:-1])
        per_episode = {
            "episode_return": episode.episode_return,
            "planning_seconds_per_step": float(episode.planning_seconds.mean()),
            "simulated_steps_per_second": episode.simulated_steps_per_second,
            "physics_steps_per_second": episode.physics_steps_per_second,
            "episode_seconds": episode_report.episode_seconds,
            "simulation_worker_restarts": episode_report.worker_restarts,
        }
        if episode.success is not None:
            per_episode["success"] = float(episode.success)
            per_episode["goal_steps"] = float(episode.goal_steps)
        per_step = {
            "step/reward": episode.rewards,
            "step/return": np.cumsum(episode.rewards),
            "step/planning_seconds": episode.planning_seconds,
            "step/trajectories": episode.trajectories,
            "step/best_cost": episode.best_costs,
        }
        self.tracker.log_episode(active.run_id, episode_report.episode, offset, per_step, per_episode)
        figure = report.episode_figure(
            f"{trial_label(active.trial)} episode {episode_report.episode} (return {episode.episode_return:.1f})",
            episode.rewards,
            episode.planning_seconds,
        )
        self.tracker.log_figure(active.run_id, figure, f"episodes/episode_{episode_report.episode:03d}.png")
        report.close(figure)

    def _finish_trial(self, active: ActiveTrial) -> report.TrialResult:
        results = [r.result for r in active.reports]
        successes = [float(r.success) for r in results if r.success is not None]
        seconds = float(np.mean(np.concatenate([r.planning_seconds for r in results])))
        summary = {
            "mean_return": float(np.mean([r.episode_return for r in results])),
            "mean_planning_seconds_per_step": seconds,
        }
        if successes:
            summary["success_rate"] = float(np.mean(successes))
        self.tracker.end_trial(active.run_id, FINISHED, summary)
        config = active.trial.config
        return report.TrialResult(
            trial_key=active.trial.key,
            task=config.task,
            algorithm=config.planner.algorithm,
            budget=config.planner.budget or 0,
            seed=config.seed,
            episode_return=summary["mean_return"],
            success=summary.get("success_rate"),
            seconds_per_step=seconds,
        )

    def _previous_results(self, parent_id: str) -> list[report.TrialResult]:
        """Trials finished before a resume, for the summary."""
        results = []
        for run in self.tracker.trial_runs(parent_id):
            if run.status != FINISHED or run.superseded or "mean_return" not in run.metrics:
                continue
            results.append(trial_result_from_run(run))
        return results

    def _poll_progress(self) -> None:
        import ray

        for active in self._active:
            if active.progress_ref is None:
                active.progress_ref = active.runner.progress.remote()
            ready, _ = ray.wait([active.progress_ref], timeout=0)
            if ready:
                try:
                    active.progress = ray.get(active.progress_ref)
                except Exception:  # a dying runner; its episode reference reports why
                    pass
                active.progress_ref = None

    # ------------------------------------------------------------- sweep
    def _end_sweep(self, parent_id, groups, table, completed, failed) -> None:
        import tempfile
        from pathlib import Path

        with tempfile.TemporaryDirectory() as directory:
            artifacts = []
            (Path(directory) / "summary.txt").write_text(table + "\n")
            (Path(directory) / "summary.csv").write_text(report.to_csv(groups))
            artifacts += [Path(directory) / "summary.txt", Path(directory) / "summary.csv"]
            if groups:
                figure = report.budget_figure(groups, self.sweep.metric.name)
                figure.savefig(Path(directory) / "budget_curve.png", dpi=110)
                report.close(figure)
                artifacts.append(Path(directory) / "budget_curve.png")
            summary = {"trials_finished": completed, "trials_failed": failed}
            self.tracker.end_sweep(parent_id, FINISHED, summary, {"icemlab.failed_trials": str(failed)}, artifacts)

    def _abort(self, parent_id: str) -> None:
        """Ctrl-C: the running trials' runs and the sweep's end KILLED, then their actors are stopped."""
        active = list(getattr(self, "_active", []))
        for trial in active:
            self.tracker.end_trial(trial.run_id, KILLED, error="interrupted (Ctrl-C)")
        self.tracker.end_sweep(parent_id, KILLED, {}, {"icemlab.interrupted": "true"})
        for trial in active:
            try:
                self._end_attempt(trial)
            except Exception:  # Ray itself may be going down with the same signal
                pass


def trial_result_from_run(run: TrialRun) -> report.TrialResult:
    """A finished child run read back from MLflow, reduced for reports."""
    budget = run.params.get("planner.budget", "None")
    return report.TrialResult(
        trial_key=run.trial_key,
        task=run.params.get("task", "?"),
        algorithm=run.params.get("planner.algorithm", "?"),
        budget=0 if budget == "None" else int(budget),
        seed=int(run.params.get("seed", "0")),
        episode_return=run.metrics.get("mean_return", float("nan")),
        success=run.metrics.get("success_rate"),
        seconds_per_step=run.metrics.get("mean_planning_seconds_per_step", float("nan")),
    )


def _error_text(error: BaseException) -> str:
    text = str(error)
    if not text:
        text = "".join(traceback.format_exception(error))
    return text
