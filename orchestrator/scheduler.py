"""The Ray driver: places trial groups, runs their rounds, survives faults, logs everything.

``ray.init()`` starts a local single-node Ray by default; an address connects
to an existing cluster. Each trial runs as a group of actors placed at once
(orchestrator/placement.py): a ProgramRunner hosting the trial's program and
the workers of the roles the program declared. The driver asks the runner for
one round at a time; each round comes back with its report and a checkpoint,
and the driver (the only process that writes to MLflow) logs the report and
stores the checkpoint in the trial's run. Nothing here knows any method.

Faults (orchestrator/failures.py): a lost process (an actor, process or node
gone) restarts the trial's group from its last checkpoint, after a backoff,
up to ``max_lost_processes`` times; an error raised by the method's code is
retried from the last checkpoint up to ``retries`` times, not again when it
repeats identically; a checkpoint the program refuses is skipped for the one
before it. Every attempt's end is recorded in the trial's run. Ctrl-C stops
the running trials and marks their runs, and the sweep's, KILLED.
"""

from __future__ import annotations

import json
import logging
import math
import os
import sys
import time
import traceback
from collections import Counter
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, NamedTuple

from orchestrator import provenance, report
from orchestrator.failures import (
    BAD_CHECKPOINT,
    CODE_ERROR,
    DRIVER_ERROR,
    DRIVER_LOST,
    INTERRUPTED,
    LOST_PROCESS,
    Failure,
    classify,
)
from orchestrator.interrupt import InterruptRequest, describe
from orchestrator.placement import TrialGroup, bundle_layout, groups_that_fit
from orchestrator.sweep import LoadedSweep, Trial
from orchestrator.tracking import (
    CORE_SECONDS_PER_WORK,
    FAILED,
    FINISHED,
    KILLED,
    PARAM_THREADS,
    ROUND_SECONDS,
    RUNNING,
    TAG_DRIVER,
    TAG_PLANNED_ROUNDS,
    TAG_ROUND_WORK,
    TAG_THREADS,
    TAG_THREADS_CHANGED,
    Tracker,
    TrialRun,
    encode_round_work,
    live_driver,
)
from workers.methods import METHODS, RoleWorkerLost

POLL_SECONDS = 0.5
BACKOFF_SECONDS = (1.0, 2.0, 5.0, 10.0, 30.0)
"""Wait before restarting a trial after its n-th lost process (the last value repeats)."""
TABLE_SETTLE_SECONDS = 0.5
"""Wait before Ray's actor table is read as an attempt ends. A worker killed moments before (beside the loss the
attempt failed on, or with the Ctrl-C) is counted by the GCS only once its node has told it, some milliseconds
later; read at once, the table would miss that loss, and the actors' teardown that follows leaves no later look."""

log = logging.getLogger(__name__)


def icemlab_version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("icemlab")
    except PackageNotFoundError:
        return "dev"


class ResourceError(ValueError):
    """A trial that needs more CPUs than the cluster has: it could never be placed."""


class PhysicsChangedError(ValueError):
    """A resume whose finished trials ran with other physics packages than this process."""


class SweepBusyError(ValueError):
    """A resume of a sweep whose driver is still running: two drivers would run its trials twice."""


def _print_notice(message: str) -> None:
    print(f"icemlab: note: {message}", file=sys.stderr)


def trial_label(trial: Trial) -> str:
    """A short name for a trial: task, the method's labels, variant and seed."""
    config = trial.config
    program = METHODS[config.method]
    parts = [config.task, *program.label_text(program.labels(config.spec()))]
    if trial.variant:
        parts.append(trial.variant)
    return "/".join(parts) + f"/s{config.seed}"


@dataclass
class TrialState:
    """A trial across its attempts."""

    trial: Trial
    total_rounds: int
    run_id: str | None = None
    attempts: int = 0
    retries_left: int = 0
    lost_left: int = 0
    lost: int = 0
    """Lost processes since the trial last completed a round: the step of the backoff."""
    recovered: int = 0
    """Role workers lost and recovered inside an attempt, over all attempts."""
    last_signature: str | None = None
    bad_checkpoints: set[int] = field(default_factory=set)
    logged_rounds: set[int] = field(default_factory=set)
    rounds_done: int = 0
    not_before: float = 0.0
    threads: int | None = None
    """CPUs per unit of work of the trial's latest attempt (from its run on a resume)."""
    round_work: tuple[float, ...] = ()
    """Each round's expected wall time relative to the others (Program.round_work); empty: all alike."""
    launched_here: bool = False
    """Whether this driver launched an attempt of the trial (its run is then this driver's to close)."""
    adopted: bool = False
    """Whether its run was found RUNNING by this resume, left so by a driver that is gone (its loss is recorded):
    this driver closes it too if it stops before launching the trial again."""
    closed_here: bool = False
    """Whether this driver ended the trial's run (FINISHED or FAILED)."""

    def work_until(self, rounds: float) -> float:
        """The work of the first ``rounds`` rounds (at most all of them); a fraction counts that share of the
        next round."""
        rounds = min(max(rounds, 0.0), self.total_rounds)
        if not self.round_work:
            return rounds
        whole = min(int(rounds), len(self.round_work))
        done = sum(self.round_work[:whole])
        if whole < len(self.round_work):
            done += (rounds - whole) * self.round_work[whole]
        return done

    def backoff(self) -> float:
        """Seconds to wait before the attempt after a lost process: growing while no round completes."""
        seconds = BACKOFF_SECONDS[min(self.lost, len(BACKOFF_SECONDS) - 1)]
        self.lost += 1
        return seconds

    def progressed(self) -> None:
        """A round completed: the next loss is not part of a crash loop, so its backoff starts over."""
        self.lost = 0


def checked_round_work(work: Sequence[float], planned: int) -> tuple[float, ...]:
    """A program's round weights if there is one finite, non-negative weight per planned round; else none (the
    rounds count alike), with a warning: a method's mistake must not skew every time to go."""
    work = tuple(float(w) for w in work)
    if len(work) == planned and all(math.isfinite(w) and w >= 0 for w in work):
        return work
    log.warning("round_work gave %d weights for %d rounds (or a negative one); the rounds count alike", len(work),
                planned)  # fmt: skip
    return ()


def time_to_go(
    states: Sequence[TrialState], in_round: Mapping[int, float], work_at_start: float, elapsed: float
) -> float | None:
    """Seconds until the trials' planned rounds are done, at the pace of the work done in this session.

    Rounds weigh by their expected wall time (TrialState.round_work): an MBRL trial's frozen row takes many
    iterations' time, so counting rounds alike would promise minutes for hours.

    Args:
        in_round: the finished fraction of the round in flight, by ``id`` of its trial's state.
        work_at_start: the work done before this session (it says nothing about this session's pace).
    """
    done = sum(s.work_until(s.rounds_done + in_round.get(id(s), 0.0)) for s in states) - work_at_start
    if done <= 0:
        return None
    remaining = sum(s.work_until(s.total_rounds) for s in states) - work_at_start - done
    return remaining * elapsed / done


@dataclass
class Attempt:
    """One attempt of a trial: its actor group and the call in flight."""

    state: TrialState
    group: TrialGroup
    phase: str = "placing"
    """placing (waiting for the group's CPUs), restoring (from a checkpoint) or running (a round)."""
    ref: Any = None
    round_index: int = 0
    checkpoint_round: int | None = None
    machine_ref: Any = None
    progress: dict[str, Any] = field(default_factory=dict)
    progress_ref: Any = None
    rss_mb: float | None = None
    logged_a_round: bool = False
    """Whether this attempt has logged a round (the first it logs may be one a crash left logged in part)."""
    restarts_seen: dict[str, int] = field(default_factory=dict)
    """Restarts of each stateless role's workers already recorded (see :meth:`SweepScheduler._record_restarts`)."""
    reported: Counter[str] = field(default_factory=Counter)
    """Stateful workers' losses the runner reported (recovered, or the failure's own), by role."""
    accounted: Counter[str] = field(default_factory=Counter)
    """Stateful workers' losses recorded so far, by role, from whichever source told first: the runner's reports or
    Ray's actor table (see :meth:`SweepScheduler._reported_losses` and :meth:`SweepScheduler._unreported`)."""


class SweepState(NamedTuple):
    """What the progress display shows."""

    name: str
    total: int
    done: int
    failed: int
    running: list[tuple[str, dict[str, Any]]]
    """(trial label, progress: round, rounds, fraction, text) per running trial."""
    elapsed: float
    eta: float | None


class SweepOutcome(NamedTuple):
    parent_run_id: str
    finished: int
    failed: int
    skipped: int
    """Trials already FINISHED in MLflow before this run (resume)."""
    table: str


MAX_CURVE_RUNS = 200
"""Curve plots read one metric history per run; above this many runs they are left out."""


def report_histories(tracker: Tracker, runs: list[TrialRun], program) -> report.Histories | None:
    """The curve metrics of finished runs, or None when there are none or too many runs."""
    if not program.curves or not runs or len(runs) > MAX_CURVE_RUNS:
        return None
    return tracker.histories([r.run_id for r in runs], program.curves)


def episode_histories(tracker: Tracker, runs: list[TrialRun], program, metric: str,
                      pairing: report.Pairing | None) -> report.Histories | None:  # fmt: skip
    """The sweep's metric per episode, for comparing variants with their baseline episode by episode; None when
    the sweep names no baseline or the method's episodes do not start alike across configurations."""
    if pairing is None or program is None or not program.paired_episodes or len(runs) > MAX_CURVE_RUNS:
        return None
    return tracker.histories([r.run_id for r in runs], [metric])


def connect_ray(address: str | None, num_cpus: int | None = None) -> bool:
    """Connect to a cluster at ``address`` or start a local one; True if this call started Ray.

    A local Ray keeps its token authentication (Ray's default, never switched
    off here) and starts no dashboard.
    """
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
        # A local Ray listens on every interface (GCS, raylet, workers); its token authentication is what
        # keeps a neighbour on the network from running code through those ports (CVE-2023-48022).
        # Ray reads the mode when it is imported, so the command line sets it first (see cli.main).
        if os.environ.get("RAY_AUTH_MODE", "token") != "token":
            raise ConnectionError(
                f"RAY_AUTH_MODE={os.environ['RAY_AUTH_MODE']}: icemlab does not start a local Ray without token "
                "authentication; unset RAY_AUTH_MODE"
            )
        ray.init(num_cpus=num_cpus or os.cpu_count(), dashboard_host="127.0.0.1", **common)
    return True


def node_cpus() -> list[float]:
    """CPUs of each live node of the connected Ray cluster."""
    import ray

    cpus = [node["Resources"].get("CPU", 0.0) for node in ray.nodes() if node.get("Alive")]
    return [c for c in cpus if c > 0] or [ray.cluster_resources().get("CPU", 1.0)]


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
        allow_physics_change: bool = False,
        notice: Callable[[str], None] | None = None,
    ):
        self.loaded = loaded
        self.sweep = loaded.sweep
        self.program = self.sweep.program
        self.tracker = tracker
        self.address = address
        self.resume = resume
        self.max_concurrent = max_concurrent
        self.display = display
        self.experiment = self.sweep.tracking.experiment or self.sweep.name
        self.counts = {"simulation": self.sweep.resources.simulation_workers} | dict(self.sweep.resources.workers)
        self._largest_group: dict[int, list[dict[str, float]]] = {}
        """The largest trial group's bundles by CPUs per unit (group_bundles looks at every trial once per unit)."""
        self._active: list[Attempt] = []
        self._parent_id: str | None = None
        """The sweep's run, once opened: what an interrupted or failing driver closes."""
        self._states: list[TrialState] = []
        """This session's trials; the ones it launched and has not closed are its to close on an abort."""
        self.allow_physics_change = allow_physics_change
        self.notice = notice or _print_notice
        self._provenance = provenance.current()

    # -------------------------------------------------------------- plan
    def _parent_run(self) -> list[TrialRun]:
        """Open the sweep's run (``_parent_id``) anew, or reopen it on --resume; return its trial runs so far."""
        if self.resume:
            previous = self.tracker.find_sweep_run(self.experiment, self.sweep.name)
            if previous is not None:
                runs = self.tracker.trial_runs(previous.run_id)
                if not self.allow_physics_change:
                    self._refuse_mixed_physics(runs)
                if previous.status == RUNNING:
                    self._record_a_lost_driver(previous, runs)
                # Known before it is reopened: a store failing half-way through (after the status is RUNNING) is
                # then recorded on the run and the run closed, not left RUNNING for the next resume to take for a
                # lost driver.
                self._parent_id = previous.run_id
                self.tracker.reopen_sweep(
                    previous.run_id, self.loaded.file_hash, len(self.loaded.trials), self.loaded.text
                )
                return runs
        self._parent_id = self.tracker.start_sweep(
            self.experiment,
            self.sweep.name,
            self.loaded.file_hash,
            None,  # logged below, once the run's id is held: a failure or Ctrl-C while it is logged closes the run
            self.sweep.tracking.tags,
            icemlab_version(),
            len(self.loaded.trials),
        )
        self.tracker.record_sweep_file(self._parent_id, self.loaded.text)
        return []

    def _record_a_lost_driver(self, sweep_run, trial_runs) -> None:
        """A sweep run still RUNNING at a resume lost its driver without a word (a driver that stops by itself
        closes its runs, see run()): say so in the sweep's run and in each trial run it left RUNNING, so the
        lost attempts are failures in MLflow like any other. Their rounds continue from the last checkpoint."""
        host, pid = ((sweep_run.tags.get(TAG_DRIVER) or "").split("|") + ["", ""])[:2]
        who = f"the driver (pid {pid} on {host})" if pid else "the driver"
        cause = f"{who} ended without closing the run (killed, out of memory, or its machine lost)"
        detail = "Found RUNNING by `icemlab run --resume`, which continues the trial from its last checkpoint.\n"
        self.tracker.record_sweep_failure(sweep_run.run_id, DRIVER_LOST, cause, detail)
        planned = {trial.key for trial in self.loaded.trials}
        for run in trial_runs:
            if run.status != RUNNING:
                continue
            # An attempt with a record ended before the driver did (a trial waiting out a retry's backoff), or
            # was found lost by an earlier resume whose own driver was lost before it launched the trial again.
            recorded = f"failures/attempt_{run.attempts:03d}_"
            if not any(path.startswith(recorded) for path in self.tracker.list_files(run.run_id, "failures")):
                self.tracker.record_failure(run.run_id, run.attempts, DRIVER_LOST, cause, detail)
            if run.trial_key not in planned:
                # The sweep was edited before this resume (a seed dropped, a value changed): no driver will adopt
                # the run, which would stay RUNNING under a closed sweep. Its checkpoints stay; restoring the
                # trial to the file resumes it.
                self.tracker.note(run.run_id, "closed by a resume: this trial is no longer in the sweep file")
                self.tracker.end_trial(run.run_id, KILLED)

    def _refuse_a_busy_resume(self) -> None:
        """A resume while the sweep's driver still runs (on this host) would run its trials twice."""
        previous = self.tracker.find_sweep_run(self.experiment, self.sweep.name) if self.resume else None
        driver = live_driver(previous.tags.get(TAG_DRIVER)) if previous and previous.status == RUNNING else None
        if driver is not None:
            raise SweepBusyError(
                f"sweep {self.sweep.name} is still being run by the driver with pid {driver} on this host; "
                f"nothing was started. Wait for it (icemlab status {self.loaded.path}), or stop it with "
                f"kill -INT {driver} and resume then"
            )

    def group_bundles(self, unit: int) -> list[dict[str, float]]:
        """The placement-group bundles of the sweep's largest trial when a unit of work gets ``unit`` CPUs.

        Trials of one sweep may hold different groups (a napsp variant with a distance trainer holds more than
        one without): laid out for the first only, a larger one could wait for CPUs that never come.
        """
        if unit not in self._largest_group:
            layouts = []
            for trial in self.loaded.trials:
                spec = trial.config.spec()
                roles = [role for role in self.program.roles_for(spec, unit, self.counts) if role.count]
                layouts.append(bundle_layout(self.program.runner_cpus(spec, unit), roles).bundles)
            self._largest_group[unit] = max(
                layouts, key=lambda bundles: (sum(b["CPU"] for b in bundles), max(b["CPU"] for b in bundles))
            )
        return self._largest_group[unit]

    def group_cpus(self, unit: int) -> float:
        """CPUs one trial's group holds when a unit of work gets ``unit`` CPUs."""
        return sum(bundle["CPU"] for bundle in self.group_bundles(unit))

    def layout(
        self, nodes: float | Sequence[float], pending: int, threads: int | None = None
    ) -> tuple[int, int]:
        """(CPUs per unit of work, concurrent trials) on nodes with these CPUs (one number: one node).

        ``threads`` fixes the CPUs per unit of work in place of the sweep's ``resources.threads_per_worker``.
        Raises ResourceError when not even one trial can be placed: more CPUs than the cluster has, or a
        bundle (one actor's CPUs, which live on one node) larger than every node.
        """
        per_node = sorted([float(nodes)] if isinstance(nodes, (int, float)) else map(float, nodes), reverse=True)
        cpus, largest = sum(per_node), per_node[0] if per_node else 0.0
        if threads is None:
            threads = self.sweep.resources.threads_per_worker
        if threads is None:
            # Enough trials to use every CPU once, the rest of the CPUs as threads.
            concurrent = max(1, min(pending, int(cpus // self.group_cpus(1))))
            if self.max_concurrent:
                concurrent = min(concurrent, self.max_concurrent)
            threads = max(1, int(cpus // (concurrent * self.group_cpus(1))))
            # A unit's CPUs are one actor's bundle, which lives on one node.
            threads = max(1, min(threads, int(largest)))
        need = self.group_cpus(threads)
        if need > cpus:
            raise ResourceError(
                f"a trial of this sweep needs {need:g} CPUs (its runner and the workers of its roles), but the "
                f"Ray cluster has {cpus:g}; lower resources.simulation_workers, resources.workers or "
                "resources.threads_per_worker, or add nodes"
            )
        bundles = self.group_bundles(threads)
        concurrent = groups_that_fit(bundles, per_node, max(1, int(cpus // need)))
        if concurrent == 0:
            sizes = sorted({bundle["CPU"] for bundle in bundles if bundle["CPU"]}, reverse=True)
            raise ResourceError(
                f"a trial of this sweep reserves bundles of {', '.join(f'{s:g}' for s in sizes)} CPUs, each on one "
                f"node, and the Ray cluster's nodes have {', '.join(f'{c:g}' for c in per_node)} CPUs, so they "
                "cannot all be placed; lower resources.threads_per_worker or add larger nodes"
            )
        if self.max_concurrent:
            concurrent = min(concurrent, self.max_concurrent)
        return threads, concurrent

    # --------------------------------------------------------------- run
    def run(self) -> SweepOutcome:
        import ray

        self._refuse_a_busy_resume()
        started_ray = connect_ray(self.address)  # before any MLflow run exists: a bad address leaves no trace
        try:
            # Ctrl-C from here on is a flag, acted on where the runs it must close are known: one that raised
            # while the sweep's run was being opened or a lost driver recorded would leave the sweep RUNNING.
            with InterruptRequest() as interrupt:
                cpus = node_cpus()
                self.layout(cpus, 1)  # a sweep that can never be placed is refused before anything is logged
                states = self._pending_states(self._parent_run())
                skipped = len(self.loaded.trials) - len(states)
                threads, concurrent = self._layout_to_continue(cpus, states)
                return self._drive(self._parent_id, states, skipped, threads, concurrent, interrupt)
        except KeyboardInterrupt as stop:
            if self._parent_id is not None:
                # A Ctrl-C pressed again (or a SIGTERM sent again) while the runs are closed would leave them RUNNING
                # half-way: it waits for the closing (a third one still stops it at once).
                with InterruptRequest():
                    self._abort(self._parent_id, INTERRUPTED, f"interrupted ({describe(stop)})", "")
            raise
        except Exception as error:
            # The driver itself failed (the tracking store, a round report it could not log, ...): say so in
            # MLflow rather than leave the runs RUNNING; the trials continue with --resume.
            if self._parent_id is not None:
                cause = f"the driver stopped: {type(error).__name__}: {error}"
                try:
                    self._abort(self._parent_id, DRIVER_ERROR, cause, traceback.format_exc())
                    error.recorded_in_mlflow = True  # type: ignore[attr-defined]  # read by the CLI's message
                except Exception as recording:  # the store itself may be what failed
                    log.error("the driver's failure could not be recorded in MLflow: %s", recording)
            raise
        finally:
            for attempt in list(self._active):
                attempt.group.teardown()
            if started_ray:
                ray.shutdown()

    def _pending_states(self, previous_runs: list[TrialRun]) -> list[TrialState]:
        """A state per trial not yet FINISHED, carrying on from its run where an earlier driver left one."""
        by_key: dict[str, TrialRun] = {}
        for run in previous_runs:
            if by_key.get(run.trial_key) is None or by_key[run.trial_key].status != FINISHED:
                by_key[run.trial_key] = run
        states = []
        for trial in self.loaded.trials:
            previous = by_key.get(trial.key)
            if previous is not None and previous.status == FINISHED:
                continue
            spec = trial.config.spec()
            planned = self.program.planned_rounds(spec)
            state = TrialState(
                trial,
                planned,
                retries_left=self.sweep.retries,
                lost_left=self.sweep.max_lost_processes,
                round_work=checked_round_work(self.program.round_work(spec, self.counts), planned),
            )
            if previous is not None:
                state.run_id = previous.run_id
                state.adopted = previous.status == RUNNING
                state.attempts = previous.attempts
                state.recovered = self.tracker.recoveries(previous.run_id)  # numbered on, not over
                state.logged_rounds = self.tracker.logged_rounds(previous.run_id)
                state.rounds_done = len(state.logged_rounds)
                state.threads = previous.threads_per_worker
            states.append(state)
        return states

    def _drive(self, parent_id, states, skipped, threads, concurrent, interrupt) -> SweepOutcome:
        import ray

        queue = list(states)
        self._states = list(states)
        done = failed = 0
        started = time.monotonic()
        last_display = 0.0
        work_at_start = sum(s.work_until(s.rounds_done) for s in states)
        self._threads = threads

        while queue or self._active:
            interrupt.raise_if_requested()
            now = time.monotonic()
            while len(self._active) < concurrent:
                ready = [s for s in queue if s.not_before <= now]
                if not ready:
                    break
                queue.remove(ready[0])
                self._active.append(self._launch(ready[0]))

            refs = [a.ref for a in self._active]
            finished_refs = ray.wait(refs, num_returns=1, timeout=POLL_SECONDS)[0] if refs else []
            if not refs:
                time.sleep(POLL_SECONDS)  # every pending trial is backing off
            interrupt.raise_if_requested()
            for ref in finished_refs:
                attempt = next(a for a in self._active if a.ref == ref)
                try:
                    value = ray.get(ref)
                except Exception as error:  # noqa: BLE001 - every failure is classified and recorded
                    outcome = self._failed(attempt, classify(error, attempt.rss_mb))
                    if outcome == "retry":
                        queue.append(attempt.state)
                    else:
                        failed += 1
                    continue
                outcome = self._advance(attempt, value)
                if outcome == "finished":
                    done += 1
                elif outcome == "failed":
                    failed += 1

            self._poll_progress()
            now = time.monotonic()
            if self.display is not None and (now - last_display >= POLL_SECONDS or not self._active):
                last_display = now
                in_round = {id(a.state): a.progress.get("fraction", 0.0) for a in self._active if a.phase == "running"}
                eta = time_to_go(states, in_round, work_at_start, now - started)
                self.display(
                    SweepState(
                        self.sweep.name,
                        len(self.loaded.trials),
                        skipped + done,
                        failed,
                        [(trial_label(a.state.trial), self._shown_progress(a)) for a in self._active],
                        now - started,
                        eta,
                    )
                )

        table = self.finish_sweep(parent_id, done + skipped, failed)
        return SweepOutcome(parent_id, done, failed, skipped, table)

    def _layout_to_continue(self, cpus: float | Sequence[float], states: list[TrialState]) -> tuple[int, int]:
        """The layout, keeping the thread count the started trials ran with when the sweep does not fix one.

        Torch sums in another order with another thread count, so a network trained on after a resume with
        other threads rounds differently from an uninterrupted run (measured on HalfCheetah APEX: one thread
        against two differs from the first training on); with the count it began with, a resumed trial
        repeats the uninterrupted one bit for bit.
        """
        began = {s.threads for s in states if s.rounds_done} - {None}
        if self.sweep.resources.threads_per_worker is None and len(began) == 1:
            try:
                return self.layout(cpus, len(states), threads=began.pop())
            except ResourceError:
                pass  # the cluster is smaller than the one they began on: lay out anew
        return self.layout(cpus, len(states))

    def _record_threads(self, state: TrialState) -> None:
        """Tag the attempt's thread count, and say so where a started trial continues with another one."""
        tags = {TAG_THREADS: str(self._threads)}
        if state.rounds_done and state.threads is not None and state.threads != self._threads:
            tags[TAG_THREADS_CHANGED] = f"{state.threads} -> {self._threads}"
            self.notice(
                f"{trial_label(state.trial)} ran with {state.threads} thread(s) per worker and continues with "
                f"{self._threads}: torch sums in another order with another thread count, so its figures may "
                "differ from an uninterrupted run's; `resources: {threads_per_worker: "
                f"{state.threads}}}` continues it as it began"
            )
        state.threads = self._threads
        self.tracker.set_tags(state.run_id, tags)

    def _refuse_mixed_physics(self, runs: list[TrialRun]) -> None:
        """Stop a resume whose finished trials ran another MuJoCo or gymnasium-robotics than this one."""
        for run in runs:
            if run.status != FINISHED:
                continue
            changes = provenance.physics_changes(run.versions)
            if changes:
                differences = ", ".join(f"{p} {before} then, {now} now" for p, (before, now) in changes.items())
                raise PhysicsChangedError(
                    f"{self.loaded.path}: finished trials of sweep {self.sweep.name} ran another simulator "
                    f"({differences}; run {run.run_id}); resuming would mix their results with new ones in one "
                    "table. Run the sweep anew (without --resume), or pass --allow-physics-change to mix them."
                )

    # ------------------------------------------------------------ trials
    def _launch(self, state: TrialState) -> Attempt:
        trial, config = state.trial, state.trial.config
        state.attempts += 1
        state.launched_here = True
        params = config.flat() | {
            PARAM_THREADS: self._threads,
            "resources.simulation_workers": self.sweep.resources.simulation_workers,
        }
        if trial.variant:
            params["variant"] = trial.variant
        artifacts = {"trial.json": json.dumps(config.canonical(), indent=2, sort_keys=True)}
        if state.run_id is None:
            tags = {"task": config.task, "method": config.method, "seed": str(config.seed)}
            tags |= METHODS[config.method].labels(config.spec())
            state.run_id = self.tracker.start_trial(
                self._parent_id,
                trial.key,
                name=f"{trial_label(trial)}#{trial.key[:6]}",
                params=params,
                tags=tags,
                artifacts=artifacts,
                variant=trial.variant,
                overrides=trial.overrides,
            )
        else:
            # A driver killed right after creating the run may have left its params or trial.json unwritten.
            self.tracker.reopen_trial(state.run_id, state.attempts, params, artifacts)
        self.tracker.record_provenance(state.run_id, self._provenance)  # the code that runs (or continues) it
        self.tracker.set_tags(  # for `icemlab status`
            state.run_id,
            {TAG_PLANNED_ROUNDS: str(state.total_rounds), TAG_ROUND_WORK: encode_round_work(state.round_work)},
        )
        self._record_threads(state)
        group = TrialGroup(config.spec(), self._threads, self.counts, self.sweep.max_lost_processes)
        return Attempt(state, group, "placing", group.ready())

    def _advance(self, attempt: Attempt, value: Any) -> str | None:
        """Move an attempt on after its call returned: "finished" when its trial finished, "failed" when the
        round's recoveries spent the lost-process budget past its end, else None."""
        import ray

        state = attempt.state
        if attempt.phase == "placing":
            runner = attempt.group.start(recoveries=state.lost_left)
            attempt.machine_ref = runner.machine.remote()
            stored, notes = self.tracker.load_checkpoint(state.run_id, skip=state.bad_checkpoints)
            for note in notes:
                self.tracker.note(state.run_id, note)
            if stored is not None:
                attempt.phase, attempt.checkpoint_round = "restoring", stored.round_index
                attempt.ref = runner.restore.remote(stored.data)
            else:
                attempt.phase, attempt.round_index = "running", 0
                attempt.ref = runner.run_round.remote(0)
            return None
        if attempt.phase == "restoring":
            if self._restored_after_the_last_round(state, int(value)):
                # The driver died after the last checkpoint and before the run was closed: the summary was
                # written before that checkpoint, so closing the run is all that is left. No round ends here to
                # read Ray's table: a stateful worker lost before the restore's loader call is read now.
                self._record_restarts(attempt, "its trial finished")
                return self._close_finished(attempt)
            attempt.phase, attempt.round_index = "running", int(value)
            attempt.ref = attempt.group.runner.run_round.remote(attempt.round_index)
            attempt.progress = {}  # the ETA must not count an earlier round's fraction as this one's
            return None

        round_report, data, recovered = value
        self._record_recoveries(state, self._reported_losses(attempt, recovered))
        self._record_restarts(attempt, "its round ended")
        if attempt.machine_ref is not None:  # answered long before the round's result
            machine = ray.get(attempt.machine_ref)
            self.tracker.record_machine(state.run_id, machine)
            attempt.machine_ref = None
        if not round_report.done:
            # The next round starts before this one is logged: logging overlaps with work.
            attempt.round_index = round_report.index + 1
            attempt.ref = attempt.group.runner.run_round.remote(attempt.round_index)
            attempt.progress = {}  # the finished round's fraction (about 1) is not the next one's
        if round_report.index not in state.logged_rounds:
            self.tracker.log_round(
                state.run_id,
                round_report.index,
                round_report.step,
                round_report.metrics,
                round_report.series,
                round_report.series_start,
                [(a.path, a.data) for a in round_report.artifacts],
                round_report.seconds,
                after_a_crash=state.attempts > 1 and not attempt.logged_a_round,
            )
            state.logged_rounds.add(round_report.index)
            attempt.logged_a_round = True
        if round_report.done:
            # Summary, last checkpoint, then FINISHED: a FINISHED run is never resumed, so a run closed before its
            # last checkpoint was written would keep the final model nowhere. A driver killed before the
            # checkpoint is complete runs the last round again on --resume (the summary is kept once); one killed
            # after it restores that checkpoint and only closes the run.
            summary = dict(round_report.summary) | self._cost(state, attempt)
            self.tracker.record_summary(state.run_id, summary, last_round=round_report.index)
        self.tracker.save_checkpoint(state.run_id, round_report.index, data)
        state.bad_checkpoints.discard(round_report.index)  # written anew: the refused one is gone
        state.rounds_done = max(state.rounds_done, round_report.index + 1)
        state.progressed()
        if not round_report.done:
            if state.lost_left < 0:  # the round's recoveries went past the budget: the trial stops at this round
                self._failed(attempt, self._budget_spent(state))
                return "failed"
            return None
        return self._close_finished(attempt)

    def _restored_after_the_last_round(self, state: TrialState, next_round: int) -> bool:
        """Whether a restored checkpoint is the one written after the trial's last round: the round its summary was
        written at (a program may end before its planned rounds), else the last planned one. A summary of a later
        round than the checkpoint's means the last checkpoint was never written: that round runs again."""
        summarised = self.tracker.summarised_round(state.run_id)
        return next_round >= (summarised + 1 if summarised is not None else state.total_rounds)

    def _close_finished(self, attempt: Attempt) -> str:
        """End a trial whose last round is logged, summarised and checkpointed: its run FINISHED."""
        state = attempt.state
        self.tracker.end_trial(state.run_id, FINISHED)
        state.closed_here = True
        state.rounds_done = state.total_rounds
        self._end_attempt(attempt)
        return "finished"

    def _record_recoveries(self, state: TrialState, causes: Sequence[str]) -> None:
        """Stateful workers lost and recovered in place by the runner: they spend the lost-process budget."""
        for cause in causes:
            state.lost_left -= 1
            state.recovered += 1
            self.tracker.record_recovery(state.run_id, state.recovered, LOST_PROCESS, cause)

    def _record_restarts(self, attempt: Attempt, when: str) -> None:
        """Workers Ray restarted that no report of the runner's accounts for, recorded as recoveries that spend the
        budget: stateless ones (their calls were retried and the trial went on untouched, but each was a lost
        process) and unreported stateful ones (:meth:`_unreported`).

        Args:
            when: the moment of the look, for the stateful causes ("its round ended").
        """
        self._record_recoveries(attempt.state, self._new_restarts(attempt) + self._unreported(attempt, when))

    def _new_restarts(self, attempt: Attempt) -> list[str]:
        """Causes of the stateless workers Ray restarted since the last look (which they are marked seen by)."""
        causes = []
        for role, count in attempt.group.stateless_restarts().items():
            lost = count - attempt.restarts_seen.get(role, 0)
            if lost > 0:
                cause = f"a worker of role {role!r} was lost; Ray restarted it and retried its call (stateless)"
                causes += [cause] * lost
                attempt.restarts_seen[role] = count
        return causes

    def _reported_losses(self, attempt: Attempt, causes: Sequence[str]) -> list[str]:
        """Of the stateful losses the runner reports, those not yet recorded from Ray's table, marked recorded.

        Both sources count the same restarts, each possibly late: the runner reports a loss only when a call
        trips over it (with the round's result or error), and the table may lag the runner. So each role's
        recorded count is the larger of the two, and a loss is recorded by whichever tells first. Marked before
        they are recorded: a store that fails half-way must not make an abort's table read record them again.
        """
        new = []
        for cause in causes:
            role = RoleWorkerLost.role_in(cause)
            attempt.reported[role] += 1
            if attempt.reported[role] > attempt.accounted[role]:
                attempt.accounted[role] += 1
                new.append(cause)
        return new

    def _unreported(self, attempt: Attempt, when: str) -> list[str]:
        """Causes of the stateful restarts in Ray's table beyond those accounted for, marked accounted.

        The runner never reports a worker lost between calls whose next call is its state loader (a restore for
        another loss, or an attempt's start, hands it its state), and a runner lost (or stopped by Ctrl-C) later in
        the round takes its report with it. Read at every round's end, at the trial's end and when an attempt
        ends; a loss the runner reports later is then not recorded again (:meth:`_reported_losses`).

        Args:
            when: the moment of the look, for the cause ("its round ended", "the attempt ended (lost_process)").
        """
        causes = []
        for role, count in attempt.group.stateful_restarts().items():
            unseen = count - attempt.accounted[role]
            if unseen > 0:
                cause = (
                    f"a worker of role {role!r} was lost and Ray restarted it; no report of the trial's runner "
                    f"accounted for it when {when} (read from Ray's actor table)"
                )
                causes += [cause] * unseen
                attempt.accounted[role] = count
        return causes

    def _budget_spent(self, state: TrialState) -> Failure:
        """The failure of a trial whose recoveries in place (Ray restarts each worker up to the whole budget, and
        the runner was handed what was left when its attempt began) went past ``max_lost_processes``."""
        budget = self.sweep.max_lost_processes
        cause = (
            f"{budget - state.lost_left} processes lost, more than max_lost_processes = {budget}; the last round "
            "completed is checkpointed: raise max_lost_processes and --resume to continue"
        )
        return Failure(LOST_PROCESS, cause, cause, "lost-process budget spent")

    def _cost(self, state: TrialState, attempt: Attempt) -> dict[str, float]:
        """Core-seconds per unit of the method's work, from the rounds' seconds: what later plans estimate from."""
        seconds = sum(value for _, value in self.tracker.metric_history(state.run_id, ROUND_SECONDS))
        work = self.program.work(state.trial.config.spec())
        return {CORE_SECONDS_PER_WORK: seconds * attempt.group.cpus / work} if work > 0 and seconds > 0 else {}

    def _failed(self, attempt: Attempt, failure: Failure) -> str:
        """Record a failed attempt and decide: "retry" (queued again) or "failed" (the trial is FAILED)."""
        state = attempt.state
        recovered = self._reported_losses(attempt, failure.recovered)  # made in the round before it failed
        # The loss this failure is about is charged as the failed attempt, not as a recovery, unless Ray's table told
        # of it first (a worker lost between rounds, read at the round's end): that recovery already charged it.
        charged = False
        if failure.role is not None:
            charged = not self._reported_losses(attempt, [str(RoleWorkerLost(failure.role, failure.cause))])
        time.sleep(TABLE_SETTLE_SECONDS)
        restarted = self._new_restarts(attempt) + self._unreported(attempt, f"the attempt ended ({failure.kind})")
        self._end_attempt(attempt)  # after the table reads: they need the actors
        repeat = failure.kind == CODE_ERROR and failure.signature == state.last_signature
        detail = "the same error as an earlier attempt (see its file)" if repeat else failure.detail
        self._record_recoveries(state, recovered + restarted)
        self.tracker.record_failure(state.run_id, state.attempts, failure.kind, failure.cause, detail)
        if failure.kind == BAD_CHECKPOINT and attempt.checkpoint_round is not None:
            state.bad_checkpoints.add(attempt.checkpoint_round)
            return "retry"
        if failure.kind == LOST_PROCESS and (charged or state.lost_left > 0):
            if not charged:
                state.lost_left -= 1
            state.not_before = time.monotonic() + state.backoff()
            return "retry"
        if failure.kind == CODE_ERROR and not repeat and state.retries_left > 0:
            state.retries_left -= 1
            state.last_signature = failure.signature
            return "retry"
        self.tracker.end_trial(state.run_id, FAILED)
        state.closed_here = True
        return "failed"

    def _end_attempt(self, attempt: Attempt) -> None:
        if attempt in self._active:
            self._active.remove(attempt)
        attempt.group.teardown()

    def _shown_progress(self, attempt: Attempt) -> dict[str, Any]:
        state = attempt.state
        # While restoring, the round to show is the checkpoint's: round_index still holds the new attempt's 0.
        round_index = attempt.checkpoint_round if attempt.phase == "restoring" else attempt.round_index
        shown = {"round": round_index, "rounds": state.total_rounds, "phase": attempt.phase}
        if attempt.phase == "running":
            shown |= {k: attempt.progress.get(k) for k in ("fraction", "text") if k in attempt.progress}
        return shown

    def _poll_progress(self) -> None:
        import ray

        for attempt in self._active:
            if attempt.phase != "running":
                continue
            if attempt.progress_ref is None:
                attempt.progress_ref = attempt.group.runner.progress.remote()
            ready, _ = ray.wait([attempt.progress_ref], timeout=0)
            if ready:
                try:
                    reply = ray.get(attempt.progress_ref)
                except Exception:  # a dying runner; its round reference reports why
                    reply = {}
                # A poll sent during the round before may be answered after the next began: its fraction (about
                # 1) is not the new round's.
                if reply.get("round") == attempt.round_index:
                    attempt.progress = reply
                attempt.rss_mb = reply.get("rss_mb", attempt.rss_mb)
                attempt.progress_ref = None

    # ------------------------------------------------------------- sweep
    def finish_sweep(self, parent_id: str, completed: int, failed: int) -> str:
        """Summary table and plots of every finished trial of the parent run, on the parent run."""
        import tempfile
        from pathlib import Path

        runs = [r for r in self.tracker.trial_runs(parent_id) if r.status == FINISHED]
        planned = {trial.key for trial in self.loaded.trials}
        metric, pairing = self.sweep.metric_name(), report.pairing(self.sweep)
        episodes = episode_histories(self.tracker, runs, self.program, metric, pairing)
        summary = report.summarize(
            runs, metric, self.sweep.metric.mode, self.loaded.references, planned, pairing, episodes
        )
        table = report.format_table(summary)
        histories = report_histories(self.tracker, runs, self.program)
        with tempfile.TemporaryDirectory() as directory:
            artifacts = report.write_files(summary, Path(directory), histories)
            totals = {"trials_finished": completed, "trials_failed": failed}
            self.tracker.end_sweep(parent_id, FINISHED, totals, failed_trials=failed, artifacts=artifacts)
        return table

    def _abort(self, parent_id: str, kind: str, cause: str, detail: str) -> None:
        """Ctrl-C or a driver error: the runs this session opened and left unfinished end KILLED with the cause
        (also those waiting out a retry's backoff, and one whose launch or failure record the error broke off),
        the sweep KILLED (FAILED for a driver error).

        The actors stop first (that needs no MLflow: a failing store must not hold the cluster's CPUs through
        its retries), then each run is recorded on its own, so one refused write does not leave the rest RUNNING;
        the first error of the store is raised at the end."""
        lost: dict[int, list[str]] = {}  # workers lost in the rounds cut short, read while the actors exist
        if self._active:
            time.sleep(TABLE_SETTLE_SECONDS)  # once for all of them
        for attempt in list(self._active):
            try:
                ended = f"the attempt ended ({kind})"
                lost[id(attempt.state)] = self._new_restarts(attempt) + self._unreported(attempt, ended)
            except Exception:  # noqa: BLE001 - the cluster's table may be going down with the same signal
                pass
            try:
                self._end_attempt(attempt)
            except Exception:  # Ray itself may be going down with the same signal
                pass
        problems: list[Exception] = []
        # A trial whose launch failed before its run was created has no run to close. An adopted run not launched
        # again is closed too, rather than left RUNNING under a closed sweep, without a second record of its last
        # attempt (whose loss the resume recorded).
        closing = [s for s in self._states if (s.launched_here or s.adopted) and not s.closed_here]
        for state in [s for s in closing if s.run_id is not None]:
            try:  # on its own: a refused recovery record must not keep the run from being closed
                self._record_recoveries(state, lost.get(id(state), []))
            except Exception as error:  # noqa: BLE001
                problems.append(error)
            try:
                run = self.tracker.trial_run(state.run_id)
                if run is not None and run.status == RUNNING:
                    if state.launched_here:
                        self.tracker.record_failure(state.run_id, state.attempts, kind, cause, detail)
                    self.tracker.end_trial(state.run_id, KILLED)
            except Exception as error:  # noqa: BLE001 - the others are still recorded
                problems.append(error)
        try:
            if kind == INTERRUPTED:
                self.tracker.end_sweep(parent_id, KILLED, {}, interrupted=True)
            else:
                self.tracker.record_sweep_failure(parent_id, kind, cause, detail)
                self.tracker.end_sweep(parent_id, FAILED, {})
        except Exception as error:  # noqa: BLE001
            problems.append(error)
        if problems:
            raise problems[0]