"""A plan before a sweep starts: what would run, what is done already, how long it would take.

Costs are in core-seconds per unit of the method's work (MPC: per environment
step), taken from the store's finished trials of the same task, method and
labels (for MPC: algorithm, budget, horizon and particles), or, when there
are none, from a few seconds of calibration on this machine. Wall time
follows the scheduler's own layout: how many trials run at once with how
many CPUs each, on this machine or on a cluster of N CPUs, plus Ray's start
and each trial's start-up.
"""

from __future__ import annotations

import math
import os
import statistics
from typing import NamedTuple

from orchestrator.sweep import LoadedSweep, Trial
from orchestrator.tracking import FINISHED, Tracker

RAY_START_SECONDS = 10.0
"""Starting a local Ray and opening the store (measured 6-8 s and 4 s on a 2-core machine)."""
TRIAL_START_SECONDS = 4.0
"""Placing a trial's actors and building its environments (2-5 s measured on a 2-core machine)."""


class Estimate(NamedTuple):
    core_seconds: float
    """CPU time of all trials still to run."""
    source: str
    """Where the cost per unit of work came from."""


class SweepPlan(NamedTuple):
    trials: list[Trial]
    finished: set[str]
    """Keys of trials already finished in the sweep's latest run (a --resume skips them)."""
    estimate: Estimate | None
    cost_per_trial: dict[str, float]
    """Core-seconds per pending trial."""

    @property
    def pending(self) -> list[Trial]:
        return [t for t in self.trials if t.key not in self.finished]


def finished_keys(loaded: LoadedSweep, tracker: Tracker | None) -> set[str]:
    if tracker is None:
        return set()
    experiment = loaded.sweep.tracking.experiment or loaded.sweep.name
    parent = tracker.find_sweep_run(experiment, loaded.sweep.name)
    if parent is None:
        return set()
    return {r.trial_key for r in tracker.trial_runs(parent.run_id) if r.status == FINISHED}


def cost_per_work(loaded: LoadedSweep, trial: Trial, tracker: Tracker | None, cache: dict) -> tuple[float, str] | None:
    """(core-seconds per unit of work, where it came from) for a trial, or None."""
    program = loaded.sweep.program
    spec = trial.config.spec()
    tags = {"task": spec.task, "method": spec.method} | program.labels(spec)
    key = tuple(sorted(tags.items()))
    if key not in cache:
        past = tracker.past_costs(tags) if tracker is not None else []
        if past:
            cache[key] = (statistics.median(past), f"{len(past)} past run(s)")
        else:
            measured = program.calibrate(spec, 1)
            cache[key] = None if measured is None else (measured, "a calibration here")
    return cache[key]


def plan_sweep(loaded: LoadedSweep, tracker: Tracker | None) -> SweepPlan:
    finished = finished_keys(loaded, tracker)
    program = loaded.sweep.program
    cache: dict = {}
    costs: dict[str, float] = {}
    sources = set()
    for trial in loaded.trials:
        if trial.key in finished:
            continue
        cost = cost_per_work(loaded, trial, tracker, cache)
        if cost is None:
            return SweepPlan(loaded.trials, finished, None, {})
        costs[trial.key] = cost[0] * program.work(trial.config.spec())
        sources.add(cost[1])
    estimate = Estimate(sum(costs.values()), ", ".join(sorted(sources))) if costs else Estimate(0.0, "nothing to run")
    return SweepPlan(loaded.trials, finished, estimate, costs)


def wall_seconds(loaded: LoadedSweep, plan: SweepPlan, cpus: int) -> float:
    """Expected wall time of the pending trials on ``cpus`` CPUs, with the scheduler's layout."""
    from orchestrator.scheduler import SweepScheduler

    pending = plan.pending
    if not pending:
        return 0.0
    scheduler = SweepScheduler(loaded, tracker=None)  # only its layout rules are used
    threads, concurrent = scheduler.layout(cpus, len(pending))
    group = scheduler.group_cpus(threads)
    durations = sorted((plan.cost_per_trial[t.key] / group for t in pending), reverse=True)
    # Longest first onto the lane that frees up first, as the scheduler's queue does for equal trials.
    lanes = [0.0] * concurrent
    for duration in durations:
        lanes[lanes.index(min(lanes))] += duration + TRIAL_START_SECONDS
    return max(lanes) + RAY_START_SECONDS


def describe(loaded: LoadedSweep, plan: SweepPlan, cluster_cpus: int) -> list[str]:
    """Lines for the command line: counts, core-hours and wall times here and on a cluster."""
    pending = plan.pending
    lines = [f"plan: {len(pending)} trial(s) to run, {len(plan.finished)} already finished (a --resume skips them)"]
    if not pending:
        return lines
    if plan.estimate is None:
        lines.append("  no time estimate: no past runs of these configurations and no calibration for this method")
        return lines
    here = os.cpu_count() or 1
    lines.append(
        f"  about {plan.estimate.core_seconds / 3600:.2f} core-hours (cost per step from {plan.estimate.source})"
    )
    lines.append(f"  this machine ({here} CPUs): about {duration_text(wall_seconds(loaded, plan, here))}")
    if cluster_cpus != here:
        cluster_seconds = wall_seconds(loaded, plan, cluster_cpus)
        lines.append(f"  a cluster of {cluster_cpus} CPUs: about {duration_text(cluster_seconds)}")
    return lines


def duration_text(seconds: float) -> str:
    """'2 h 05 min' or '4 min 10 s': a duration as estimates are told."""
    seconds = int(math.ceil(seconds))
    hours, rest = divmod(seconds, 3600)
    minutes, seconds = divmod(rest, 60)
    return f"{hours} h {minutes:02d} min" if hours else f"{minutes} min {seconds:02d} s"
