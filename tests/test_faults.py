"""Sustained faults (marker: slow): a random worker-side actor SIGKILLed every 15 s through a sweep.

Four HalfCheetah trials (budget 50, two episodes of 300 steps, two remote
simulation workers each, default retry settings) run once undisturbed and once
while a killer thread SIGKILLs a random actor of the running trials (the
ProgramRunner or a SimulationWorker) every 15 s. Every trial must finish
exactly once with results identical to the undisturbed run, in at most twice
its wall time. About ten minutes on two cores.

The learning methods get the same treatment with their smoke sweeps and their
stateful or relabeling roles as the targets: APEX's RelabelWorker and policy
trainer, the MBRL EnsembleTrainer, neural APSP's DistanceTrainer.
"""

from __future__ import annotations

import os
import random
import signal
import threading
import time
from pathlib import Path

import pytest
import ray
from helpers import sweep_runs, write_sweep

from orchestrator.scheduler import SweepScheduler
from orchestrator.sweep import load_sweep
from orchestrator.tracking import FINISHED, Tracker, default_tracking_uri

pytestmark = pytest.mark.slow

KILL_EVERY_SECONDS = 15.0
"""The killer's period, or a sixth of the fault-free run where that is shorter (the smoke sweeps take seconds):
every stormy run sees kills."""
MIN_KILL_PERIOD = 2.0


def halfcheetah_sweep(directory):
    return write_sweep(
        directory,
        "sustained",
        task="halfcheetah_running",
        base={"planner": {"budget": 50}, "episodes": 2, "max_steps": 300},
        seeds=[0, 1, 2, 3],
        resources={"simulation_workers": 2, "threads_per_worker": 1},
    )


class Killer(threading.Thread):
    """SIGKILLs a random actor of the scheduler's running trials every ``period`` seconds.

    ``roles`` limits the targets to those roles ("runner" is the trial's ProgramRunner); None targets all.
    """

    def __init__(self, scheduler: SweepScheduler, period: float, roles: tuple[str, ...] | None = None, seed: int = 0,
                 limit: int | None = None):  # fmt: skip
        super().__init__(daemon=True)
        self.limit = limit
        self.scheduler, self.period, self.roles = scheduler, period, roles
        self.random = random.Random(seed)
        self.stopped = threading.Event()
        self.kills: list[tuple[float, str]] = []

    def run(self) -> None:
        started = time.monotonic()
        while not self.stopped.wait(self.period):
            if self.limit is not None and len(self.kills) >= self.limit:
                return
            running = [a for a in list(self.scheduler._active) if a.phase == "running"]
            actors = [
                (name, actor)
                for a in running
                for name, actor in self._actors(a)
                if self.roles is None or name in self.roles
            ]
            if not actors:
                continue
            name, actor = self.random.choice(actors)
            pid = self._pid(actor)
            if pid is None:
                continue
            try:
                os.kill(pid, signal.SIGKILL)
            except ProcessLookupError:  # it died or finished meanwhile
                continue
            self.kills.append((time.monotonic() - started, name))

    @staticmethod
    def _pid(actor) -> int | None:
        """The actor's process, from Ray's actor table; None unless it is alive.

        Asking the actor itself (``actor.pid.remote()``) would queue behind the call it is running: a role worker
        runs one call at a time, so a busy trainer could never be hit. The table needs no dashboard.
        """
        from ray._private import state

        try:
            info = state.actors(actor_id=actor._actor_id.hex())
        except Exception:  # noqa: BLE001 - an actor table read racing the actor's end: try the next period
            return None
        return info.get("Pid") or None if info.get("State") == "ALIVE" else None

    @staticmethod
    def _actors(attempt):
        yield "runner", attempt.group.runner
        for role, workers in attempt.group.workers.items():
            for worker in workers:
                yield role, worker


def run_sweep(directory, sweep, killer_period: float | None, roles: tuple[str, ...] | None = None, limit=None):
    """Run ``sweep`` with a fresh store in ``directory``, with a killer if a period is given."""
    loaded = load_sweep(sweep)
    tracker = Tracker(default_tracking_uri(directory))
    scheduler = SweepScheduler(loaded, tracker)
    killer = Killer(scheduler, killer_period, roles, limit=limit) if killer_period else None
    started = time.monotonic()
    if killer:
        killer.start()
    try:
        outcome = scheduler.run()
    finally:
        if killer:
            killer.stopped.set()
    seconds = time.monotonic() - started
    _, children = sweep_runs(tracker.uri, loaded.sweep.name)
    return outcome, children, seconds, killer, tracker


def calm_and_stormy(tmp_path, sweep, roles=None):
    """The sweep undisturbed, then under kills; both stores fresh, one local Ray for both."""
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    try:
        calm_dir, stormy_dir = tmp_path / "calm", tmp_path / "stormy"
        calm_dir.mkdir()
        stormy_dir.mkdir()
        calm = run_sweep(calm_dir, sweep, None)
        period = max(MIN_KILL_PERIOD, min(KILL_EVERY_SECONDS, calm[2] / 6))
        # Every kill that lands spends one of the trial's lost processes: stop short of the budget, which is
        # what a storm beyond it should exhaust.
        limit = load_sweep(sweep).sweep.max_lost_processes - 2
        stormy = run_sweep(stormy_dir, sweep, period, roles, limit)
    finally:
        ray.shutdown()
    (_, _, calm_seconds, _, _), (_, _, seconds, killer, _) = calm, stormy
    kinds = [name for _, name in killer.kills]
    print(
        f"\n{sweep.name}: fault-free {calm_seconds:.0f} s; with a kill every {killer.period:.1f} s {seconds:.0f} s "
        f"(x{seconds / calm_seconds:.2f}); {len(kinds)} kills: "
        + ", ".join(f"{kinds.count(k)} {k}" for k in sorted(set(kinds)))
    )
    return calm, stormy


def failed_errors(children) -> list[str]:
    """What ended the trials that did not finish, for the assertion's message."""
    return [f"{c.trial_key}: {c.error_class}: {c.error}" for c in children if c.status != FINISHED]


def assert_no_step_logged_twice(tracker: Tracker, child) -> None:
    for key in child.metrics:
        steps = [s for s, _ in tracker.metric_history(child.run_id, key)]
        assert len(steps) == len(set(steps)), f"{key}: a step logged twice"


def test_sustained_kills_cost_at_most_the_round_in_flight(tmp_path):
    sweep = halfcheetah_sweep(tmp_path)
    (calm, calm_children, _, _, _), (stormy, children, _, killer, tracker) = calm_and_stormy(
        tmp_path, sweep
    )
    kinds = [name for _, name in killer.kills]
    assert (calm.finished, calm.failed) == (4, 0)
    assert (stormy.finished, stormy.failed) == (4, 0), failed_errors(children)
    assert len(children) == 4 and all(c.status == FINISHED for c in children)  # each trial finished exactly once
    assert kinds.count("runner") >= 1 and kinds.count("simulation") >= 1
    expected = {c.trial_key: c.metrics["mean_return"] for c in calm_children}
    assert {c.trial_key: c.metrics["mean_return"] for c in children} == expected  # identical results
    for child in children:
        steps = [s for s, _ in tracker.metric_history(child.run_id, "step/reward")]
        assert sorted(steps) == list(range(600))  # no metric step lost or logged twice
        assert child.metrics.get("failures/code_error") is None  # kills never spend the code-error retries


SMOKE = Path(__file__).resolve().parents[1] / "sweeps" / "smoke"


@pytest.mark.parametrize(
    ("method", "roles"),
    [("apex", ("relabel", "trainer")), ("mbrl", ("trainer",)), ("napsp", ("distance",))],
)
def test_a_learning_method_survives_sustained_kills_of_its_workers(tmp_path, method, roles):
    """The method's smoke sweep, its relabeling or training actors SIGKILLed every 15 s."""
    sweep = SMOKE / f"{method}.yaml"
    metric = load_sweep(sweep).sweep.program.metrics
    (calm, calm_children, _, _, _), (stormy, children, _, killer, tracker) = calm_and_stormy(
        tmp_path, sweep, roles
    )
    assert killer.kills, "no actor of the targeted roles was ever running"
    assert (calm.finished, calm.failed) == (stormy.finished, stormy.failed) == (len(calm_children), 0), (
        failed_errors(children)
    )
    assert len(children) == len(calm_children) and all(c.status == FINISHED for c in children)
    summary = sorted(set(metric.values()))

    def results(runs) -> dict[str, list]:  # nan (a figure with nothing to measure yet) compares as itself
        return {c.trial_key: [repr(c.metrics.get(k)) for k in summary] for c in runs}

    assert results(children) == results(calm_children)  # identical results
    for child in children:
        assert_no_step_logged_twice(tracker, child)
        assert child.metrics.get("failures/code_error") is None


def test_a_memory_kill_is_a_lost_process_that_says_why(tmp_path):
    """Ray's memory monitor kills the trial's workers (threshold forced down): recorded with its cause."""
    from helpers import cli

    sweep = write_sweep(
        tmp_path, "memory", method="toy", algorithm=None, base={"rounds": 3, "steps": 10, "train_seconds": 2.0}
    )
    sweep.write_text(sweep.read_text() + "max_lost_processes: 1\n")
    pressure = {"RAY_memory_usage_threshold": "0.01", "RAY_memory_monitor_refresh_ms": "100"}
    result = cli("run", str(sweep), "--quiet", cwd=tmp_path, env=pressure)
    assert result.returncode == 1
    _, (child,) = sweep_runs(default_tracking_uri(tmp_path), "memory")
    # The budget of one is spent by the second loss: the first retried (two attempts), or recorded as a recovery
    # (the monitor also took the trainer, which Ray restarted, before the runner: one attempt).
    recoveries = Tracker(default_tracking_uri(tmp_path)).metric_history(child.run_id, "recovered/lost_process")
    assert child.error_class == "lost_process" and child.attempts + len(recoveries) == 2
    assert "killed for memory" in child.error and "--max-concurrent" in child.error
    assert "the node had" in child.error and child.metrics["failures/lost_process"] == 1.0
    status = cli("status", str(sweep), cwd=tmp_path)
    assert "lost_process: OutOfMemoryError: a process was killed for memory" in status.stdout
