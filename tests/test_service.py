"""The service end to end: real Ray, real MLflow (SQLite), real faults.

* a sweep through the CLI lands in MLflow as a parent run with one FINISHED
  child per trial, params, metrics, artifacts and checkpoints;
* a method whose code raises fails after its retries, each resuming from the
  last checkpoint, with the traceback in MLflow and in ``icemlab status``;
* a killed stateless worker (SimulationWorker) is restarted and its call
  retried; a killed stateful one (a trainer) costs the round in flight, and
  the trial resumes from its last checkpoint with the same final result;
* a driver killed with SIGKILL loses nothing: ``--resume`` continues every
  trial from its last completed round, no round or metric step twice;
* a trial's actors are placed all at once or not at all;
* Ctrl-C stops the sweep and marks the unfinished runs KILLED.
"""

from __future__ import annotations

import contextlib
import os
import signal
import threading
import time
from collections import Counter
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import ray
import toy_method
from helpers import cli, kill_group, start_cli, sweep_runs, wait_for, write_sweep

from orchestrator.placement import TrialGroup, bundle_layout, groups_that_fit
from orchestrator.scheduler import ResourceError, SweepScheduler
from orchestrator.sweep import load_sweep
from orchestrator.tracking import (
    FAILED,
    FINISHED,
    KILLED,
    PARAM_THREADS,
    RUNNING,
    TAG_THREADS,
    TAG_THREADS_CHANGED,
    Tracker,
    default_tracking_uri,
)
from workers.methods import METHODS, RoleSpec, run_locally


@pytest.fixture(scope="module")
def local_ray():
    """One local Ray for the in-process scheduler tests of this module."""
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    yield
    ray.shutdown()


def toy_sweep(directory, name, seeds=(0,), retries=1, **settings):
    base = {"rounds": 4, "steps": 10} | settings
    return write_sweep(directory, name, method="toy", base=base, algorithm=None, seeds=list(seeds), retries=retries)


def history(tracker: Tracker, run_id: str, key: str) -> list[tuple[int, float]]:
    return sorted(tracker.metric_history(run_id, key))


def uninterrupted_toy_losses(sweep) -> list[float]:
    trial = load_sweep(sweep).trials[0].config
    return [r.metrics["loss"] for r in run_locally(METHODS["toy"], trial.spec())]


def test_cli_sweep_lands_in_mlflow(tmp_path):
    sweep = write_sweep(
        tmp_path,
        "landing",
        base={"planner": {"budget": 50, "horizon": 10}, "max_steps": 8, "episodes": 2, "round_steps": 5},
        parameters={"algorithm": {"values": ["icem", "cem_mpc"]}},
        variants=[{"name": "full"}, {"name": "short", "planner.horizon": 5}],
        baseline="full",
    )
    result = cli("run", str(sweep), "--quiet", cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    table = [line for line in result.stdout.splitlines() if line.startswith("point_reach")]  # the summary table
    # Episode i starts alike in every variant: each is paired with its baseline episode by episode.
    assert len(table) == 4 and sum("vs full (paired t-test, 2 episodes, p=" in line for line in table) == 2

    parent, children = sweep_runs(default_tracking_uri(tmp_path), "landing")
    assert parent.status == FINISHED
    assert {c.status for c in children} == {FINISHED} and len(children) == 4
    assert {c.trial_key for c in children} == {t.key for t in load_sweep(sweep).trials}
    for child in children:
        assert child.params["task"] == "point_reach" and child.params["planner.budget"] == "50"
        assert child.params["method"] == "mpc" and child.tags["method"] == "mpc"
        assert child.tags["task"] == "point_reach" and child.tags["seed"] == "0"
        assert child.tags["algorithm"] in ("icem", "cem_mpc") and child.tags["budget"] == "50"
        assert np.isfinite(child.metrics["episode_return"]) and child.metrics["simulated_steps_per_second"] > 0
    tracker = Tracker(default_tracking_uri(tmp_path))
    run_id = children[0].run_id
    steps = history(tracker, run_id, "step/reward")
    assert [s for s, _ in steps] == list(range(16))  # 2 episodes x 8 steps, counted across episodes, once each
    assert [s for s, _ in history(tracker, run_id, "icemlab.round")] == [0, 1, 2, 3]  # 2 rounds per episode
    assert children[0].planned_rounds == 4  # told by `icemlab status` as "rounds 4/4"
    assert children[0].round_work == [1.0] * 4  # which weighs them alike in its time to go
    episodes = history(tracker, run_id, "episode_return")
    assert [s for s, _ in episodes] == [0, 1]
    assert children[0].metrics["mean_return"] == pytest.approx(np.mean([v for _, v in episodes]))
    assert {"sweep.yaml", "summary.csv", "summary.txt", "curves.png"} <= set(tracker.list_files(parent.run_id))
    assert set(tracker.list_files(run_id, "episodes")) == {
        f"episodes/episode_00{i}.{ext}" for i in (0, 1) for ext in ("png", "npz")
    }
    assert {"trial.json", "checkpoints"} <= set(tracker.list_files(run_id))

    # Progress against the sweep's plan, recorded when it starts and again when it resumes.
    assert "finished 4 of 4  running 0  failed 0  killed 0" in cli("status", cwd=tmp_path).stdout
    began = tracker.sweeps()[0].session_started
    assert began is not None and began <= time.time()
    first = tracker.recorded_sweep(parent.run_id)
    tracker.reopen_sweep(parent.run_id, "edited", planned_trials=6, yaml_text=first + "# edited\n")
    assert "finished 4 of 6" in cli("status", str(sweep), cwd=tmp_path).stdout
    # The edited file is what a report by name plans from; the first one is kept.
    assert tracker.recorded_sweep(parent.run_id) == first + "# edited\n"
    (kept,) = tracker.list_files(parent.run_id, "sweep_history")
    assert tracker.download(parent.run_id, kept, tmp_path / "kept").read_text() == first
    assert tracker.sweeps()[0].session_started > began  # a resume starts the session `icemlab status` paces


def test_a_pending_actor_call_says_whether_it_is_done_without_waiting(local_ray):
    """Progress counts finished calls on actors with done(): False while the call runs, True once it returned."""
    from orchestrator.placement import RayPending

    @ray.remote
    class Gate:
        def __init__(self):
            self.open = False

        def release(self):
            self.open = True

        def wait(self):
            while not self.open:
                time.sleep(0.01)
            return "through"

    gate = Gate.options(max_concurrency=2).remote()
    pending = RayPending("gate", gate.wait.remote())
    assert not pending.done()  # the call cannot return before the gate opens
    ray.get(gate.release.remote())
    assert pending.result() == "through" and pending.done()


@pytest.mark.slow  # a whole sweep through the CLI; the default suite keeps the Ray-free checks
def test_code_error_fails_after_retries_from_the_last_checkpoint(tmp_path, local_ray):
    """A method that raises on round 2: two attempts (the repeat is identical), rounds 0-1 logged once."""
    sweep = toy_sweep(tmp_path, "raising", retries=3, fail_on_round=2)
    tracker = Tracker(default_tracking_uri(tmp_path))
    outcome = SweepScheduler(load_sweep(sweep), tracker).run()
    assert (outcome.finished, outcome.failed) == (0, 1)

    parent, (child,) = sweep_runs(tracker.uri, "raising")
    assert parent.tags["icemlab.failed_trials"] == "1"
    assert child.status == FAILED and child.attempts == 2  # retries 3, but the identical repeat is not retried
    assert child.error_class == "code_error" and "fails on round 2" in child.error
    assert child.metrics["failures/code_error"] == 1.0
    assert "failures/lost_process" not in child.metrics  # a code error is not mistaken for a lost process
    assert [s for s, _ in history(tracker, child.run_id, "icemlab.round")] == [0, 1]  # not repeated
    files = tracker.list_files(child.run_id, "failures")
    assert [f.rsplit("_", 2)[-2:] for f in sorted(files)] == [["code", "error.txt"]] * 2
    first = tmp_path / "first.txt"
    tracker.download(child.run_id, sorted(files)[0], tmp_path).rename(first)
    assert "Traceback" in first.read_text() and "toy_method.py" in first.read_text()
    assert "failures/lost_process" not in child.metrics

    status = cli("status", str(sweep), cwd=tmp_path)
    assert "FAILED" in status.stdout and "code_error: ValueError: toy method fails on round 2" in status.stdout


@pytest.mark.slow  # a whole sweep through the CLI; the default suite keeps the Ray-free checks
def test_a_refused_checkpoint_is_skipped_for_the_one_before(tmp_path, local_ray):
    """Resume from a store whose newest checkpoint was replaced by a pickle (with a matching manifest)."""
    import json
    import pickle
    from urllib.parse import urlparse

    from workers.checkpoint import digest

    cleared = tmp_path / "cleared"
    sweep = toy_sweep(tmp_path, "planted", retries=0, fail_on_round=3, fail_until_file=str(cleared))
    tracker = Tracker(default_tracking_uri(tmp_path))
    assert SweepScheduler(load_sweep(sweep), tracker).run().failed == 1  # rounds 0-2 done, round 3 raised
    _, (child,) = sweep_runs(tracker.uri, "planted")
    assert tracker.logged_rounds(child.run_id) == {0, 1, 2}

    marker = tmp_path / "pwned"
    payload = pickle.dumps(RunsCode(str(marker)))
    folder = Path(urlparse(tracker.client.get_run(child.run_id).info.artifact_uri).path) / "checkpoints/round_000002"
    (folder / "state.npz").write_bytes(payload)
    (folder / "manifest.json").write_text(json.dumps({"round": 2, "bytes": len(payload), "sha256": digest(payload)}))
    cleared.touch()

    outcome = SweepScheduler(load_sweep(sweep), tracker, resume=True).run()
    assert (outcome.finished, outcome.failed) == (1, 0)
    assert not marker.exists()  # nothing was unpickled
    _, (child,) = sweep_runs(tracker.uri, "planted")
    assert child.status == FINISHED and child.metrics["failures/bad_checkpoint"] == 1.0
    assert [s for s, _ in history(tracker, child.run_id, "icemlab.round")] == [
        0,
        1,
        2,
        3,
    ]  # round 2 redone, logged once
    assert [v for _, v in history(tracker, child.run_id, "loss")] == uninterrupted_toy_losses(sweep)


class RunsCode:
    def __init__(self, marker: str):
        self.marker = marker

    def __reduce__(self):
        return os.system, (f"touch {self.marker}",)


@pytest.mark.parametrize("resumed_with", [None, 1], ids=["threads-open", "threads-fixed"])
def test_a_resumed_trial_continues_with_the_thread_count_it_began_with(tmp_path, local_ray, resumed_with):
    """Torch rounds differently with other threads: a resume that leaves the count open keeps the trial's
    own; one that fixes another continues with it and says so, on stderr and in the run's tags."""
    cleared = tmp_path / "cleared"

    def sweep(threads):
        base = {"rounds": 3, "steps": 10, "fail_on_round": 2, "fail_until_file": str(cleared)}
        resources = {} if threads is None else {"resources": {"threads_per_worker": threads}}
        return write_sweep(tmp_path, "threads", method="toy", base=base, algorithm=None, retries=0, **resources)

    tracker = Tracker(default_tracking_uri(tmp_path))
    assert SweepScheduler(load_sweep(sweep(2)), tracker).run().failed == 1  # rounds 0-1 with two threads
    _, (child,) = sweep_runs(tracker.uri, "threads")
    assert child.tags[TAG_THREADS] == "2" and child.threads_per_worker == 2

    cleared.touch()
    notices = []
    loaded = load_sweep(sweep(resumed_with))
    assert SweepScheduler(loaded, tracker).layout(2, 1) == (1, 1)  # what the open count would be on 2 CPUs
    outcome = SweepScheduler(loaded, tracker, resume=True, notice=notices.append).run()
    assert (outcome.finished, outcome.failed) == (1, 0)
    _, (child,) = sweep_runs(tracker.uri, "threads")
    assert child.status == FINISHED and child.params[PARAM_THREADS] == "2"  # the first attempt's
    if resumed_with is None:
        assert child.tags[TAG_THREADS] == "2" and TAG_THREADS_CHANGED not in child.tags and notices == []
    else:
        assert child.tags[TAG_THREADS] == "1" and child.tags[TAG_THREADS_CHANGED] == "2 -> 1"
        (notice,) = notices
        assert notice.startswith("point_reach/s0 ran with 2 thread(s) per worker and continues with 1")
        assert "may differ from an uninterrupted run" in notice
        assert "`resources: {threads_per_worker: 2}` continues it as it began" in notice


def test_killed_simulation_worker_is_restarted_and_the_episode_completes(tmp_path, local_ray):
    """SIGKILL the remote SimulationWorker mid-episode; the result equals an undisturbed run."""
    sweep = write_sweep(
        tmp_path,
        "worker_kill",
        task="halfcheetah_running",
        base={"planner": {"budget": 100, "horizon": 30}, "max_steps": 40},
        resources={"simulation_workers": 2, "threads_per_worker": 1},
    )
    loaded = load_sweep(sweep)
    tracker = Tracker(default_tracking_uri(tmp_path))
    scheduler = SweepScheduler(loaded, tracker)
    killed = {}

    def kill_worker_mid_episode():
        def running_trial():
            active = scheduler._active
            return active[0] if active and active[0].phase == "running" else None

        def fraction_done() -> float:
            return scheduler._active[0].progress.get("fraction", 0) if scheduler._active else 1.0

        # The pid is asked for before the episode is far along: the call queues behind the worker's cost
        # evaluations, and on a busy machine its answer could otherwise arrive after the episode has ended.
        trial = wait_for(running_trial, timeout=120, interval=0.05, what="the trial to be placed")
        pid = ray.get(trial.group.workers["simulation"][0].pid.remote())
        wait_for(lambda: fraction_done() > 0.1, timeout=120, interval=0.05, what="the episode to be under way")
        os.kill(pid, signal.SIGKILL)
        killed.update(pid=pid, fraction=fraction_done())

    killer = threading.Thread(target=kill_worker_mid_episode, daemon=True)
    killer.start()
    outcome = scheduler.run()
    killer.join(timeout=5)
    assert killed, "the worker was never killed"
    assert killed["fraction"] < 1  # mid-episode
    assert (outcome.finished, outcome.failed) == (1, 0)

    _, (child,) = sweep_runs(tracker.uri, "worker_kill")
    assert child.status == FINISHED and child.attempts == 1  # absorbed by the restart, no trial restart
    assert child.metrics["simulation_worker_restarts"] >= 1  # the failure is visible in MLflow
    # ... and, read by the driver from Ray's actor table, as a recovery of the trial, as any method's would be.
    recoveries = tracker.list_files(child.run_id, "failures")
    assert recoveries and all(f.rsplit("/", 1)[-1].startswith("recovery_") for f in recoveries)
    text = tracker.download(child.run_id, recoveries[0], tmp_path / "recovery").read_text()
    assert "a worker of role 'simulation' was lost; Ray restarted it" in text
    # Costs are a pure function of state and actions, so the retried call changes nothing.
    (undisturbed,) = run_locally(METHODS["mpc"], loaded.trials[0].config.spec())
    assert child.metrics["episode_return"] == undisturbed.metrics["episode_return"]


@pytest.mark.slow  # a whole sweep through the CLI; the default suite keeps the Ray-free checks
def test_killed_trainer_is_recovered_in_place_from_the_last_round(tmp_path, local_ray):
    """SIGKILL the stateful trainer mid-training: the round is lost, the restarted trainer gets the state of the
    last completed round, the round runs again in the same attempt, and the trial ends as if unharmed."""
    sweep = toy_sweep(tmp_path, "trainer_kill", train_seconds=1.0)
    tracker = Tracker(default_tracking_uri(tmp_path))
    scheduler = SweepScheduler(load_sweep(sweep), tracker)
    killed = {}

    def kill_trainer_after_first_round():
        def trainer_in_round_two():
            active = scheduler._active
            if active and active[0].phase == "running" and active[0].round_index >= 1:
                return active[0].group.workers["trainer"][0]
            return None

        trainer = wait_for(trainer_in_round_two, timeout=120, interval=0.05, what="round 2")
        time.sleep(0.5)  # inside the training call (it sleeps 1 s first)
        pid = ray.get(trainer.pid.remote())
        os.kill(pid, signal.SIGKILL)
        killed["pid"] = pid

    killer = threading.Thread(target=kill_trainer_after_first_round, daemon=True)
    killer.start()
    outcome = scheduler.run()
    killer.join(timeout=5)
    assert killed and (outcome.finished, outcome.failed) == (1, 0)

    _, (child,) = sweep_runs(tracker.uri, "trainer_kill")
    assert child.status == FINISHED and child.attempts == 1  # no new attempt, no new actor group
    assert history(tracker, child.run_id, "recovered/lost_process") == [(1, 1.0)]
    assert "failures/lost_process" not in child.metrics
    (recovery,) = tracker.list_files(child.run_id, "failures")
    assert recovery.endswith("recovery_001_lost_process.txt")
    assert [s for s, _ in history(tracker, child.run_id, "icemlab.round")] == [0, 1, 2, 3]  # each round once
    assert [v for _, v in history(tracker, child.run_id, "weights_version")] == [1, 2, 3, 4]
    assert [v for _, v in history(tracker, child.run_id, "loss")] == uninterrupted_toy_losses(sweep)


def test_a_progress_reply_from_the_round_before_is_not_shown_as_the_next_ones(tmp_path, local_ray):
    """The runner answers progress polls while it works; a reply sent as round 1 ended (fraction 0.9) and read
    once round 2 began must not stand for round 2 (an MBRL frozen row's ETA would be hours early)."""
    from orchestrator.scheduler import Attempt

    _, scheduler, state = started_toy_trial(tmp_path, "stale")
    attempt = Attempt(state, RunnerlessGroup(), phase="running", round_index=2)
    scheduler._active = [attempt]
    attempt.progress_ref = ray.put({"round": 1, "fraction": 0.9, "text": "step 9", "rss_mb": 50.0})
    scheduler._poll_progress()
    assert attempt.progress == {} and attempt.rss_mb == 50.0 and attempt.progress_ref is None
    attempt.progress_ref = ray.put({"round": 2, "fraction": 0.2, "text": "step 2", "rss_mb": 51.0})
    scheduler._poll_progress()
    assert attempt.progress["fraction"] == 0.2


@pytest.mark.slow  # a whole sweep that waits out a worker's restart
def test_a_trainer_killed_between_calls_is_not_left_to_work_on_from_nothing(tmp_path, local_ray):
    """SIGKILL the stateful trainer while it is idle (round 3 collects its episode, held there until the trainer
    is back): Ray restarts it fresh and no call fails. The restarted trainer refuses to train until it is handed
    its state, so the round runs again from the last completed one, the loss is recorded, and the trial ends as
    if unharmed."""
    from ray._private import state as actor_table

    pause = tmp_path / "pause"
    sweep = toy_sweep(tmp_path, "idle_kill", steps=20, step_seconds=0.2, pause_file=str(pause))
    tracker = Tracker(default_tracking_uri(tmp_path))
    scheduler = SweepScheduler(load_sweep(sweep), tracker)
    killed = {}

    def kill_the_idle_trainer_in_round_three():
        def collecting_round_three():
            active = scheduler._active
            if active and active[0].phase == "running" and active[0].round_index == 2:
                if active[0].progress.get("round") == 2 and 0 < (active[0].progress.get("fraction") or 0) < 0.5:
                    return active[0].group.workers["trainer"][0]
            return None

        trainer = wait_for(collecting_round_three, timeout=120, interval=0.02, what="round 3's collection")
        pause.touch()
        info = actor_table.actors(actor_id=trainer._actor_id.hex())
        os.kill(info["Pid"], signal.SIGKILL)
        killed["pid"] = info["Pid"]

        def back_up() -> bool:
            info = actor_table.actors(actor_id=trainer._actor_id.hex())
            return info["State"] == "ALIVE" and info["NumRestarts"] == 1

        wait_for(back_up, timeout=120, interval=0.05, what="the trainer's restart")
        killed["round"] = scheduler._active[0].progress.get("round")
        pause.unlink()

    killer = threading.Thread(target=kill_the_idle_trainer_in_round_three, daemon=True)
    killer.start()
    outcome = scheduler.run()
    killer.join(timeout=5)
    assert killed.get("round") == 2 and (outcome.finished, outcome.failed) == (1, 0)

    _, (child,) = sweep_runs(tracker.uri, "idle_kill")
    assert child.status == FINISHED and child.attempts == 1
    assert history(tracker, child.run_id, "recovered/lost_process") == [(1, 1.0)]
    (recovery,) = tracker.list_files(child.run_id, "failures")
    text = tracker.download(child.run_id, recovery, tmp_path / "recovery").read_text()
    assert "restarted without its state" in text  # refused by the restarted trainer, not a failed call
    assert [v for _, v in history(tracker, child.run_id, "weights_version")] == [1, 2, 3, 4]
    assert [v for _, v in history(tracker, child.run_id, "loss")] == uninterrupted_toy_losses(sweep)


class DriverDied(BaseException):
    """Stands for the driver process dying at that point: nothing of the scheduler's handles it."""


class DyingTracker(Tracker):
    """A tracker whose driver dies (or whose store fails) at the first call of ``method`` that ``when`` matches."""

    def __init__(self, uri, method: str, when: Callable[..., bool], error: BaseException):
        super().__init__(uri)
        original = getattr(self, method)

        def dying(*args, **kwargs):
            if when(*args, **kwargs) and not self.died:
                self.died = True
                raise error
            return original(*args, **kwargs)

        self.died = False
        setattr(self, method, dying)


@contextlib.contextmanager
def dying_after_one_batch(tracker: Tracker):
    """The driver dies after the first metrics batch it sends (its later batches are never written)."""
    log_batch, sent = tracker.client.log_batch, []

    def once(*args, **kwargs):
        if sent:
            raise DriverDied()
        sent.append(log_batch(*args, **kwargs))

    tracker.client.log_batch = once
    try:
        yield
    finally:
        tracker.client.log_batch = log_batch


class RunnerlessGroup:
    """An attempt's actor group whose runner takes calls and never answers: the scheduler's own steps, no Ray."""

    class _Call:
        def remote(self, *args):
            return "ref"

    runner = type("Runner", (), {"run_round": _Call()})()
    cpus = 1

    def __init__(self, restarts: dict[str, int] | None = None, stateful: dict[str, int] | None = None):
        self.restarts = restarts or {}
        """What the group says Ray has restarted of its stateless roles so far."""
        self.stateful = stateful or {}
        """... and of its stateful roles."""

    def stateless_restarts(self) -> dict[str, int]:
        return dict(self.restarts)

    def stateful_restarts(self) -> dict[str, int]:
        return dict(self.stateful)

    def teardown(self):
        pass


def test_a_driver_killed_as_the_last_round_ends_closes_the_run_on_resume_and_goes_no_further(tmp_path, local_ray):
    """The driver dies as it closes the finished trial, after the last checkpoint: the resume restores that
    checkpoint and closes the run; it neither repeats the last round nor runs a fifth."""
    sweep = toy_sweep(tmp_path, "last_round")
    uri = default_tracking_uri(tmp_path)
    dying = DyingTracker(uri, "end_trial", lambda run_id, status, *_: status == FINISHED, DriverDied())
    with pytest.raises(DriverDied):
        SweepScheduler(load_sweep(sweep), dying).run()
    (child,) = sweep_runs(uri, "last_round")[1]
    assert child.status == RUNNING and [s for s, _ in history(dying, child.run_id, "icemlab.round")] == [0, 1, 2, 3]
    assert dying.load_checkpoint(child.run_id)[0].round_index == 3  # the final model is kept before the run closes

    tracker = Tracker(uri)
    outcome = SweepScheduler(load_sweep(sweep), tracker, resume=True).run()
    assert (outcome.finished, outcome.failed) == (1, 0)
    (child,) = sweep_runs(uri, "last_round")[1]
    assert child.status == FINISHED and child.attempts == 2
    assert [s for s, _ in history(tracker, child.run_id, "icemlab.round")] == [0, 1, 2, 3]  # each round once
    assert [v for _, v in history(tracker, child.run_id, "loss")] == uninterrupted_toy_losses(sweep)
    assert child.metrics["final_loss"] == uninterrupted_toy_losses(sweep)[-1]


def test_a_store_refusing_the_last_checkpoint_leaves_the_trial_to_resume_not_finished(tmp_path, local_ray):
    """The last round's checkpoint holds the final model (of MBRL and neural APSP, nowhere else): a store that
    refuses it must not leave the run FINISHED without it, which no resume would ever run again."""
    sweep = toy_sweep(tmp_path, "last_checkpoint")
    uri = default_tracking_uri(tmp_path)
    dying = DyingTracker(uri, "save_checkpoint", lambda run_id, index, *_: index == 3, OSError("disk full"))
    with pytest.raises(OSError, match="disk full"):
        SweepScheduler(load_sweep(sweep), dying).run()
    (child,) = sweep_runs(uri, "last_checkpoint")[1]
    assert child.status == KILLED and child.error_class == "driver_error"
    assert len(history(dying, child.run_id, "final_loss")) == 1  # the summary came before the checkpoint

    tracker = Tracker(uri)
    outcome = SweepScheduler(load_sweep(sweep), tracker, resume=True).run()
    assert (outcome.finished, outcome.failed) == (1, 0)
    (child,) = sweep_runs(uri, "last_checkpoint")[1]
    assert child.status == FINISHED and child.attempts == 2
    assert tracker.load_checkpoint(child.run_id)[0].round_index == 3
    assert [s for s, _ in history(tracker, child.run_id, "icemlab.round")] == [0, 1, 2, 3]  # round 3 ran again
    assert history(tracker, child.run_id, "final_loss") == [(0, uninterrupted_toy_losses(sweep)[-1])]


def test_a_driver_killed_between_the_summary_and_closing_the_run_logs_the_summary_once(tmp_path, local_ray):
    """The summary metrics are written, the driver dies before the run is FINISHED: the resume repeats the last
    round and closes the run without writing the summary a second time."""
    sweep = toy_sweep(tmp_path, "summary_once")
    uri = default_tracking_uri(tmp_path)
    dying = Tracker(uri)
    set_terminated = dying.client.set_terminated

    def dies_as_it_closes(run_id, status=None, *args, **kwargs):
        if status == FINISHED and dying.client.get_run(run_id).data.tags.get("icemlab.kind") == "trial":
            raise DriverDied()
        return set_terminated(run_id, status, *args, **kwargs)

    dying.client.set_terminated = dies_as_it_closes
    with pytest.raises(DriverDied):
        SweepScheduler(load_sweep(sweep), dying).run()
    (child,) = sweep_runs(uri, "summary_once")[1]
    assert child.status == RUNNING and len(history(dying, child.run_id, "final_loss")) == 1

    tracker = Tracker(uri)
    outcome = SweepScheduler(load_sweep(sweep), tracker, resume=True).run()
    assert (outcome.finished, outcome.failed) == (1, 0)
    (child,) = sweep_runs(uri, "summary_once")[1]
    assert child.status == FINISHED and child.attempts == 2
    assert history(tracker, child.run_id, "final_loss") == [(0, uninterrupted_toy_losses(sweep)[-1])]


def test_an_error_of_the_driver_is_recorded_in_mlflow_and_the_sweep_resumes(tmp_path, local_ray):
    """The tracking store refuses round 2's metrics: the error goes on to the caller, and MLflow says what
    happened (the sweep FAILED with the cause, the trial KILLED with a driver_error), not RUNNING forever."""
    sweep = toy_sweep(tmp_path, "store_error")
    uri = default_tracking_uri(tmp_path)
    dying = DyingTracker(uri, "log_round", lambda run_id, index, *_, **__: index == 2, OSError("disk full"))
    with pytest.raises(OSError, match="disk full"):
        SweepScheduler(load_sweep(sweep), dying).run()
    parent, (child,) = sweep_runs(uri, "store_error")
    assert parent.status == FAILED and parent.tags["icemlab.error_class"] == "driver_error"
    assert "OSError: disk full" in parent.tags["icemlab.error"]
    assert child.status == KILLED and child.error_class == "driver_error" and "disk full" in child.error
    assert any(f.endswith("driver_error.txt") for f in dying.list_files(child.run_id, "failures"))
    assert dying.list_files(parent.run_id, "failures") == ["failures/attempt_001_driver_error.txt"]
    status = cli("status", str(sweep), cwd=tmp_path).stdout
    assert "driver_error: the driver stopped: OSError: disk full" in status.splitlines()[1]

    tracker = Tracker(uri)
    log_round, crash_flags = tracker.log_round, []

    def spied(*args, after_a_crash=False, **kwargs):
        crash_flags.append(after_a_crash)
        log_round(*args, after_a_crash=after_a_crash, **kwargs)

    tracker.log_round = spied
    outcome = SweepScheduler(load_sweep(sweep), tracker, resume=True).run()
    assert (outcome.finished, outcome.failed) == (1, 0)
    (child,) = sweep_runs(uri, "store_error")[1]
    assert child.status == FINISHED and [s for s, _ in history(tracker, child.run_id, "icemlab.round")] == [0, 1, 2, 3]
    assert crash_flags == [True, False]  # round 2 may have been written in part; round 3 is new
    parent = sweep_runs(uri, "store_error")[0]
    assert parent.status == FINISHED and "icemlab.error" not in parent.tags  # the resumed sweep is not failing
    assert "driver_error" not in cli("status", str(sweep), cwd=tmp_path).stdout


def test_a_driver_error_the_store_cannot_record_still_reaches_the_caller(tmp_path, local_ray):
    """The store that refused a round also refuses closing the sweep: the caller gets the first error, not the
    store's second one, and is not told that MLflow knows; the trial's own run is still closed."""
    sweep = toy_sweep(tmp_path, "store_down")
    uri = default_tracking_uri(tmp_path)
    dying = DyingTracker(uri, "log_round", lambda run_id, index, *_, **__: index == 1, OSError("disk full"))

    def store_down(*args, **kwargs):
        raise RuntimeError("store down")

    dying.end_sweep = store_down
    with pytest.raises(OSError, match="disk full") as error:
        SweepScheduler(load_sweep(sweep), dying).run()
    assert not getattr(error.value, "recorded_in_mlflow", False)
    (child,) = sweep_runs(uri, "store_down")[1]
    assert child.status == KILLED and child.error_class == "driver_error"


def test_a_run_whose_launch_the_store_broke_off_is_closed_with_the_error(tmp_path, local_ray):
    """The store fails after the trial's run was opened, before its attempt was running: the run is this
    session's and must end KILLED with the cause, not stay RUNNING under a FAILED sweep."""
    sweep = toy_sweep(tmp_path, "launch_broken")
    uri = default_tracking_uri(tmp_path)
    dying = DyingTracker(uri, "record_provenance", lambda *_: True, OSError("store refused the write"))
    with pytest.raises(OSError, match="store refused"):
        SweepScheduler(load_sweep(sweep), dying).run()
    parent, (child,) = sweep_runs(uri, "launch_broken")
    assert parent.status == FAILED
    assert child.status == KILLED and child.error_class == "driver_error" and "store refused" in child.error


def test_a_lost_drivers_attempt_is_recorded_once_and_an_ended_attempt_not_again(tmp_path):
    """Two resumes may find the same trial RUNNING (the first one's driver was lost before it relaunched it), and
    a trial waiting out a retry's backoff has its attempt recorded already: neither gets a second record."""
    sweep = toy_sweep(tmp_path, "lost_twice")
    tracker = Tracker(default_tracking_uri(tmp_path))
    scheduler = SweepScheduler(load_sweep(sweep), tracker)
    parent = tracker.start_sweep("lost_twice", "lost_twice", "hash", sweep.read_text(), {}, "dev")
    lost = tracker.start_trial(parent, "lost", "lost", {"seed": 0}, {})
    waiting = tracker.start_trial(parent, "waiting", "waiting", {"seed": 0}, {})
    tracker.record_failure(waiting, 1, "lost_process", "a worker died", "")
    for _ in range(2):
        scheduler._record_a_lost_driver(tracker.find_sweep_run("lost_twice", "lost_twice"), tracker.trial_runs(parent))
    assert tracker.list_files(lost, "failures") == ["failures/attempt_001_driver_lost.txt"]
    assert history(tracker, lost, "failures/driver_lost") == [(1, 1.0)]
    assert tracker.list_files(waiting, "failures") == ["failures/attempt_001_lost_process.txt"]
    # The sweep's run keeps one record per lost driver.
    assert len(tracker.list_files(parent, "failures")) == 2


def test_a_resume_closes_the_runs_a_lost_driver_left_of_trials_no_longer_in_the_sweep(tmp_path):
    """The sweep was edited between the lost driver and the resume: no state adopts the run of a trial the file no
    longer has, so the resume closes it (with the lost attempt recorded) rather than leave it RUNNING under a
    sweep that will finish; a trial still in the file stays RUNNING for the resume to adopt."""
    sweep = toy_sweep(tmp_path, "edited")
    tracker = Tracker(default_tracking_uri(tmp_path))
    parent = tracker.start_sweep("edited", "edited", "hash", sweep.read_text(), {}, "dev")
    dropped = tracker.start_trial(parent, "0123456789abcdef", "dropped", {"seed": 7}, {})
    kept = tracker.start_trial(parent, load_sweep(sweep).trials[0].key, "kept", {"seed": 0}, {})
    scheduler = SweepScheduler(load_sweep(sweep), tracker, resume=True)
    scheduler._record_a_lost_driver(tracker.find_sweep_run("edited", "edited"), tracker.trial_runs(parent))
    assert tracker.trial_run(dropped).status == KILLED
    assert tracker.list_files(dropped, "failures") == ["failures/attempt_001_driver_lost.txt"]
    assert any("no longer in the sweep" in tracker.download(dropped, path, tmp_path / "note").read_text()
               for path in tracker.list_files(dropped, "notes"))  # fmt: skip
    assert tracker.trial_run(kept).status == RUNNING


def test_a_resumed_sweep_that_finishes_is_no_longer_marked_interrupted(tmp_path):
    from orchestrator.tracking import TAG_INTERRUPTED

    tracker = Tracker(default_tracking_uri(tmp_path))
    parent = tracker.start_sweep("again", "again", "hash", "name: again\n", {}, "dev")
    tracker.end_sweep(parent, KILLED, {}, interrupted=True)
    assert tracker.client.get_run(parent).data.tags[TAG_INTERRUPTED] == "true"
    tracker.reopen_sweep(parent, "hash", 1)
    tracker.end_sweep(parent, FINISHED, {})
    assert TAG_INTERRUPTED not in tracker.client.get_run(parent).data.tags


def test_an_abort_passes_over_a_trial_whose_run_was_never_created(tmp_path):
    """The store failed inside start_trial: the trial is launched here but has no run to close."""
    from orchestrator.scheduler import TrialState

    sweep = toy_sweep(tmp_path, "no_run")
    tracker = Tracker(default_tracking_uri(tmp_path))
    scheduler = SweepScheduler(load_sweep(sweep), tracker)
    parent = tracker.start_sweep("no_run", "no_run", "hash", sweep.read_text(), {}, "dev")
    unborn = TrialState(load_sweep(sweep).trials[0], 4, attempts=1)
    unborn.launched_here = True
    scheduler._states = [unborn]
    scheduler._abort(parent, "interrupted", "interrupted (Ctrl-C)", "")
    assert sweep_runs(default_tracking_uri(tmp_path), "no_run")[0].status == KILLED


def test_ctrl_c_while_the_sweeps_run_is_opened_ends_it_killed_not_running(tmp_path, local_ray):
    """Ctrl-C lands while the driver opens the sweep's run (or records a lost driver): the run is closed KILLED
    as for a Ctrl-C later on; left RUNNING, the next --resume would record a lost driver that was not lost."""
    sweep = toy_sweep(tmp_path, "early_ctrl_c")
    tracker = Tracker(default_tracking_uri(tmp_path))
    start_sweep = tracker.start_sweep

    def pressed_meanwhile(*args, **kwargs):
        run_id = start_sweep(*args, **kwargs)
        signal.raise_signal(signal.SIGINT)
        return run_id

    tracker.start_sweep = pressed_meanwhile
    with pytest.raises(KeyboardInterrupt):
        SweepScheduler(load_sweep(sweep), tracker).run()
    parent, children = sweep_runs(tracker.uri, "early_ctrl_c")
    assert parent.status == KILLED and children == []


def test_a_recovery_half_recorded_before_the_store_failed_is_not_recorded_again_by_the_abort(tmp_path):
    """The store takes a recovery's metric, then refuses its file: the driver error's abort reads Ray's table for
    losses the runner did not report, and must count that one as reported (one record, not two); a refused record
    there must not keep the run from being closed KILLED."""
    from orchestrator.scheduler import Attempt
    from workers.methods import RoleWorkerLost, RoundReport

    tracker, scheduler, state = started_toy_trial(tmp_path, "half_recorded_abort", lost_left=5)
    state.launched_here = True
    attempt = Attempt(state, RunnerlessGroup(stateful={"trainer": 1}), phase="running")
    scheduler._active, scheduler._states = [attempt], [state]
    log_text = tracker.client.log_text

    def refuses(*args, **kwargs):
        raise OSError("store refused")

    tracker.client.log_text = refuses
    reported = [str(RoleWorkerLost("trainer", "killed"))]
    with pytest.raises(OSError):
        scheduler._advance(attempt, (RoundReport(0, {"loss": 1.0}, step=0), b"state", reported))
    tracker.client.log_text = log_text
    scheduler._abort(tracker.find_sweep_run("half_recorded_abort", "r").run_id, "driver_error", "store refused", "")
    assert history(tracker, state.run_id, "recovered/lost_process") == [(1, 1.0)]
    assert tracker.trial_run(state.run_id).status == KILLED


def test_ctrl_c_pressed_again_while_the_runs_are_closed_lets_the_closing_finish(tmp_path, local_ray):
    """The second Ctrl-C of an impatient user lands while the interrupted sweep's run is being closed: the run
    still ends KILLED rather than RUNNING (which the next --resume would take for a lost driver)."""
    sweep = toy_sweep(tmp_path, "impatient")
    tracker = Tracker(default_tracking_uri(tmp_path))
    start_sweep, end_sweep = tracker.start_sweep, tracker.end_sweep

    def pressed(*args, **kwargs):
        run_id = start_sweep(*args, **kwargs)
        signal.raise_signal(signal.SIGINT)
        return run_id

    def pressed_again(*args, **kwargs):
        signal.raise_signal(signal.SIGINT)
        return end_sweep(*args, **kwargs)

    tracker.start_sweep, tracker.end_sweep = pressed, pressed_again
    with pytest.raises(KeyboardInterrupt):
        SweepScheduler(load_sweep(sweep), tracker).run()
    assert sweep_runs(tracker.uri, "impatient")[0].status == KILLED


def test_a_store_failing_while_a_sweep_is_reopened_leaves_it_failed_with_the_error_not_running(tmp_path, local_ray):
    """--resume reopens the sweep's run (RUNNING again), then the store refuses a tag: the error is recorded on the
    run and the run closed FAILED, rather than left RUNNING for the next resume to take for a lost driver."""
    from orchestrator.tracking import FAILED, TAG_DRIVER, TAG_ERROR_CLASS

    sweep = toy_sweep(tmp_path, "reopen_fails")
    tracker = Tracker(default_tracking_uri(tmp_path))
    parent = tracker.start_sweep("reopen_fails", "reopen_fails", "hash", sweep.read_text(), {}, "dev")
    tracker.end_sweep(parent, KILLED, {}, interrupted=True)
    set_tag = tracker.client.set_tag

    def refuses_the_driver_tag(run_id, key, value):
        if key == TAG_DRIVER:
            raise OSError("store refused")
        return set_tag(run_id, key, value)

    tracker.client.set_tag = refuses_the_driver_tag
    with pytest.raises(OSError):
        SweepScheduler(load_sweep(sweep), tracker, resume=True).run()
    tracker.client.set_tag = set_tag
    run = tracker.client.get_run(parent)
    assert run.info.status == FAILED and run.data.tags[TAG_ERROR_CLASS] == "driver_error"


@pytest.mark.parametrize("cut", ["store error", "Ctrl-C twice"])
def test_a_sweep_whose_file_could_not_be_logged_as_it_opened_is_closed_not_left_running(tmp_path, local_ray, cut):
    """The sweep's run exists, and logging its sweep file fails (the store refuses it, or an impatient user presses
    Ctrl-C twice): the run is closed (FAILED with the error, or KILLED), not left RUNNING for the next resume to
    take for a lost driver."""
    from orchestrator.tracking import FAILED

    sweep = toy_sweep(tmp_path, f"file_cut_{cut[:5]}")
    tracker = Tracker(default_tracking_uri(tmp_path))
    log_text = tracker.client.log_text

    def cut_short(run_id, text, artifact_file):
        if artifact_file == "sweep.yaml":
            if cut == "store error":
                raise OSError("store refused")
            signal.raise_signal(signal.SIGINT)
            signal.raise_signal(signal.SIGINT)
        return log_text(run_id, text, artifact_file)

    tracker.client.log_text = cut_short
    with pytest.raises(OSError if cut == "store error" else KeyboardInterrupt):
        SweepScheduler(load_sweep(sweep), tracker).run()
    tracker.client.log_text = log_text
    parent, _ = sweep_runs(tracker.uri, f"file_cut_{cut[:5]}")
    assert parent.status == (FAILED if cut == "store error" else KILLED)


def test_workers_lost_in_a_round_cut_short_by_ctrl_c_are_recorded(tmp_path):
    """Ctrl-C ends a round whose report never comes: the workers Ray restarted in it (stateless ones, and stateful
    ones the runner recovered) are read from the actor table before the actors go, and recorded."""
    from orchestrator.scheduler import Attempt

    tracker, scheduler, state = started_toy_trial(tmp_path, "cut_short", lost_left=5)
    state.launched_here = True
    attempt = Attempt(state, RunnerlessGroup({"relabel": 1}, stateful={"trainer": 1}), phase="running")
    scheduler._active, scheduler._states = [attempt], [state]
    scheduler._abort(tracker.find_sweep_run("cut_short", "r").run_id, "interrupted", "Ctrl-C", "")
    assert history(tracker, state.run_id, "recovered/lost_process") == [(1, 1.0), (2, 1.0)]
    assert tracker.trial_run(state.run_id).status == KILLED


def test_ctrl_c_also_ends_a_trial_waiting_out_a_retrys_backoff(tmp_path):
    """A trial whose process was lost waits for its retry outside the running attempts; Ctrl-C then must end its
    run KILLED too, not leave it RUNNING under a KILLED sweep."""
    from orchestrator.scheduler import TrialState

    sweep = toy_sweep(tmp_path, "backoff")
    tracker = Tracker(default_tracking_uri(tmp_path))
    scheduler = SweepScheduler(load_sweep(sweep), tracker)
    parent = tracker.start_sweep("backoff", "backoff", "hash", sweep.read_text(), {}, "dev")
    waiting = TrialState(load_sweep(sweep).trials[0], 4, attempts=1)
    waiting.run_id = tracker.start_trial(parent, waiting.trial.key, "waiting", {"seed": 0}, {})
    untouched = TrialState(load_sweep(sweep).trials[0], 4, attempts=1)  # from an earlier session, not launched
    untouched.run_id = tracker.start_trial(parent, "earlier", "earlier", {"seed": 0}, {})
    waiting.launched_here = True  # as _launch marks it (test_a_launched_trial_is_this_drivers_to_close)
    scheduler._states = [waiting, untouched]
    scheduler._abort(parent, "interrupted", "interrupted (Ctrl-C)", "")
    runs = {run.run_id: run for run in tracker.trial_runs(parent)}
    assert runs[waiting.run_id].status == KILLED and runs[waiting.run_id].error_class == "interrupted"
    assert runs[untouched.run_id].status == RUNNING  # not this session's to close


def test_ctrl_c_before_a_resume_relaunches_a_trial_a_lost_driver_left_running_closes_its_run(tmp_path):
    """A resume adopts the runs a lost driver left RUNNING; stopped before it launches one again (Ctrl-C during
    start-up, or the trial still queued), it closes that run KILLED instead of leaving it RUNNING under a KILLED
    sweep, and adds no second record of the attempt whose loss the resume recorded."""
    sweep = toy_sweep(tmp_path, "adopted")
    tracker = Tracker(default_tracking_uri(tmp_path))
    parent = tracker.start_sweep("adopted", "adopted", "hash", sweep.read_text(), {}, "dev")
    key = load_sweep(sweep).trials[0].key
    orphan = tracker.start_trial(parent, key, "orphan", {"seed": 0}, {})  # its driver is gone: still RUNNING
    tracker.record_failure(orphan, 1, "driver_lost", "the driver ended without closing the run", "")
    scheduler = SweepScheduler(load_sweep(sweep), tracker, resume=True)
    scheduler._states = scheduler._pending_states(tracker.trial_runs(parent))
    scheduler._abort(parent, "interrupted", "interrupted (Ctrl-C)", "")
    assert tracker.trial_run(orphan).status == KILLED
    assert [path for path in tracker.list_files(orphan, "failures") if "interrupted" in path] == []


def test_a_recorded_driver_counts_as_running_only_while_its_process_lives():
    """The check that refuses a second driver: a live process with the recorded start, not this process, not a
    later process that got the same pid, not a process on another host."""
    import socket
    import subprocess

    from orchestrator.tracking import live_driver, process_start, this_driver

    host = socket.gethostname()
    other = subprocess.Popen(["sleep", "30"])
    try:
        recorded = f"{host}|{other.pid}|{process_start(other.pid)}"
        assert live_driver(recorded) == other.pid
        assert live_driver(f"{host}|{other.pid}|{process_start(os.getpid())}") is None  # the pid, used again
        assert live_driver(f"elsewhere|{other.pid}|{process_start(other.pid)}") is None
    finally:
        other.kill()
        other.wait()
    assert live_driver(recorded) is None and live_driver(this_driver()) is None and live_driver(None) is None


def test_a_reopened_run_gets_the_params_and_files_a_dying_driver_left_unwritten(tmp_path):
    """A driver killed between creating a trial's run and logging its params left a run without them: the
    next attempt writes what is missing and keeps what is there (a param's value cannot change)."""
    tracker = Tracker(default_tracking_uri(tmp_path))
    parent = tracker.start_sweep("bare", "bare", "hash", "name: bare\n", {}, "dev")
    bare = tracker.start_trial(parent, "bare", "bare", {}, {})
    partial = tracker.start_trial(parent, "partial", "partial", {PARAM_THREADS: 2}, {})
    params, files = {"seed": 3, "planner.budget": 50, PARAM_THREADS: 1}, {"trial.json": "{}"}
    for run_id in (bare, partial):
        tracker.reopen_trial(run_id, 2, params, files)
    runs = {run.run_id: run for run in tracker.trial_runs(parent)}
    assert runs[bare].params == {"seed": "3", "planner.budget": "50", PARAM_THREADS: "1"}
    assert runs[partial].params[PARAM_THREADS] == "2" and runs[partial].params["seed"] == "3"
    assert all("trial.json" in tracker.list_files(run_id) for run_id in (bare, partial))
    assert runs[bare].attempts == 2


@pytest.mark.parametrize("after_a_crash", [True, False])
def test_a_round_logged_in_part_before_a_crash_is_completed_without_duplicates(tmp_path, after_a_crash):
    """A round of 1,500 steps is written in two batches; the driver dies after the first. Logged again after the
    crash, each step is in MLflow once (without the flag the first batch's steps are there twice)."""
    tracker = Tracker(default_tracking_uri(tmp_path))
    parent = tracker.start_sweep("long", "long", "hash", "name: long\n", {}, "dev")
    run_id = tracker.start_trial(parent, "trial", "trial", {"seed": 0}, {})
    series = {"step/reward": list(np.linspace(0.0, 1.0, 1500))}
    with dying_after_one_batch(tracker), pytest.raises(DriverDied):
        tracker.log_round(run_id, 0, 0, {"episode_return": 1.0}, series, 0)
    assert tracker.logged_rounds(run_id) == set()  # the marker is in the batch that was not written
    tracker.log_round(run_id, 0, 0, {"episode_return": 1.0}, series, 0, after_a_crash=after_a_crash)
    steps = Counter(s for s, _ in history(tracker, run_id, "step/reward"))
    assert sorted(steps) == list(range(1500)) and (max(steps.values()) == 1) == after_a_crash
    assert tracker.logged_rounds(run_id) == {0}


def test_a_rounds_seconds_written_before_a_crash_are_not_written_again(tmp_path):
    """999 entries and the round's seconds fill the first batch; the marker alone is in the second."""
    tracker = Tracker(default_tracking_uri(tmp_path))
    parent = tracker.start_sweep("edge", "edge", "hash", "name: edge\n", {}, "dev")
    run_id = tracker.start_trial(parent, "trial", "trial", {"seed": 0}, {})
    series = {"step/reward": [0.0] * 998}
    with dying_after_one_batch(tracker), pytest.raises(DriverDied):
        tracker.log_round(run_id, 0, 0, {"episode_return": 1.0}, series, 0, seconds=5.0)
    tracker.log_round(run_id, 0, 0, {"episode_return": 1.0}, series, 0, seconds=5.0, after_a_crash=True)
    assert history(tracker, run_id, "icemlab.round_seconds") == [(0, 5.0)]


def test_the_first_round_an_attempt_logs_is_the_one_checked_for_a_partial_log(tmp_path):
    """A resumed attempt that restored an older checkpoint first reruns rounds logged whole (skipped); the round
    after them is the one a crash may have left logged in part."""
    from orchestrator.scheduler import Attempt, TrialState
    from workers.methods import RoundReport

    sweep = toy_sweep(tmp_path, "partial")
    tracker = Tracker(default_tracking_uri(tmp_path))
    flags = []
    log_round = tracker.log_round
    tracker.log_round = lambda *args, after_a_crash=False, **kwargs: (
        flags.append(after_a_crash),
        log_round(*args, after_a_crash=after_a_crash, **kwargs),
    )
    scheduler = SweepScheduler(load_sweep(sweep), tracker)
    parent = tracker.start_sweep("partial", "partial", "hash", sweep.read_text(), {}, "dev")
    state = TrialState(load_sweep(sweep).trials[0], 4, attempts=2, logged_rounds={0, 1}, rounds_done=2)
    state.run_id = tracker.start_trial(parent, state.trial.key, "trial", {"seed": 0}, {})
    attempt = Attempt(state, RunnerlessGroup(), phase="running", round_index=1)
    for index in (1, 2, 3):
        scheduler._advance(attempt, (RoundReport(index, {"loss": 1.0}, step=index), b"state", []))
    assert flags == [True, False]  # round 1 was skipped; round 2 is checked, round 3 is new


def started_toy_trial(tmp_path, name: str, **state: Any):
    """(tracker, scheduler, trial state) of a toy sweep whose sweep and trial runs are started, no Ray: for the
    scheduler's own steps on an attempt."""
    from orchestrator.scheduler import TrialState

    sweep = toy_sweep(tmp_path, name)
    tracker = Tracker(default_tracking_uri(tmp_path))
    scheduler = SweepScheduler(load_sweep(sweep), tracker)
    parent = tracker.start_sweep(name, "r", "hash", sweep.read_text(), {}, "dev")
    trial_state = TrialState(load_sweep(sweep).trials[0], 4, attempts=1, **state)
    trial_state.run_id = tracker.start_trial(parent, trial_state.trial.key, "trial", {"seed": 0}, {})
    return tracker, scheduler, trial_state


def test_recoveries_made_before_a_round_failed_are_recorded_and_spend_the_budget(tmp_path):
    """The runner recovered a worker, then lost one with no recovery left: both losses are in MLflow and in the
    budget (before, the recovery vanished with the round and the next attempt got it back)."""
    from orchestrator.failures import LOST_PROCESS, Failure
    from orchestrator.scheduler import Attempt

    tracker, scheduler, state = started_toy_trial(tmp_path, "recovered_then_lost", lost_left=2)
    failure = Failure(LOST_PROCESS, "trainer lost", "detail", "sig", recovered=("trainer lost: first",))
    assert scheduler._failed(Attempt(state, RunnerlessGroup(), phase="running"), failure) == "retry"
    assert state.lost_left == 0 and state.recovered == 1
    assert history(tracker, state.run_id, "recovered/lost_process") == [(1, 1.0)]
    assert history(tracker, state.run_id, "failures/lost_process") == [(1, 1.0)]
    again = Failure(LOST_PROCESS, "trainer lost", "detail", "sig")
    assert scheduler._failed(Attempt(state, RunnerlessGroup(), phase="running"), again) == "failed"


def test_stateless_workers_ray_restarted_are_recorded_once_and_spend_the_budget(tmp_path):
    """A stateless worker's loss fails no call (Ray restarts it and retries), so neither the runner nor a round
    hears of it: the driver reads the restarts from the group after each round, and once more when an attempt
    fails, and records each new one once, as a recovery that spends the lost-process budget."""
    from orchestrator.failures import LOST_PROCESS, Failure
    from orchestrator.scheduler import Attempt
    from workers.methods import RoundReport

    tracker, scheduler, state = started_toy_trial(tmp_path, "restarted", lost_left=5)
    group = RunnerlessGroup({"relabel": 0, "planner": 0})
    attempt = Attempt(state, group, phase="running", round_index=0)
    group.restarts["relabel"] = 2
    scheduler._advance(attempt, (RoundReport(0, {"loss": 1.0}, step=0), b"state", []))
    scheduler._advance(attempt, (RoundReport(1, {"loss": 1.0}, step=1), b"state", []))  # nothing new
    assert history(tracker, state.run_id, "recovered/lost_process") == [(1, 1.0), (2, 1.0)]
    assert state.lost_left == 3 and state.recovered == 2
    group.restarts["planner"] = 1  # lost after the last round ended, before the attempt failed
    failure = Failure(LOST_PROCESS, "runner lost", "detail", "sig")
    assert scheduler._failed(attempt, failure) == "retry"
    files = tracker.list_files(state.run_id, "failures")
    assert sorted(f.rsplit("/", 1)[-1] for f in files) == [
        "attempt_001_lost_process.txt", "recovery_001_lost_process.txt", "recovery_002_lost_process.txt",
        "recovery_003_lost_process.txt",
    ]  # fmt: skip
    third = tracker.download(state.run_id, "failures/recovery_003_lost_process.txt", tmp_path / "r3").read_text()
    assert "role 'planner' was lost; Ray restarted it" in third
    assert state.lost_left == 1  # three restarts and the runner's loss


def test_a_stateful_recovery_whose_report_died_with_the_runner_is_recorded_from_rays_table(tmp_path):
    """The runner reports the workers it recovered with the round's result or error; a runner lost later in the
    round takes that report with it. When the attempt ends, each stateful restart Ray counted that neither a
    reported recovery nor the failure itself accounts for is recorded, and spends the budget, once."""
    from orchestrator.failures import LOST_PROCESS, Failure
    from orchestrator.scheduler import Attempt
    from workers.methods import RoleWorkerLost, RoundReport

    tracker, scheduler, state = started_toy_trial(tmp_path, "unreported", lost_left=6)
    group = RunnerlessGroup(stateful={"trainer": 1, "learner": 0})
    attempt = Attempt(state, group, phase="running", round_index=0)
    reported = [str(RoleWorkerLost("trainer", "killed"))]
    scheduler._advance(attempt, (RoundReport(0, {"loss": 1.0}, step=0), b"state", reported))
    assert state.recovered == 1 and state.lost_left == 5
    group.stateful = {"trainer": 2, "learner": 1}  # both recovered in round 1; then the runner was lost
    runner_lost = Failure(LOST_PROCESS, "ActorDiedError: the runner", "detail", "sig")
    assert scheduler._failed(attempt, runner_lost) == "retry"
    assert history(tracker, state.run_id, "recovered/lost_process") == [(1, 1.0), (2, 1.0), (3, 1.0)]
    assert state.lost_left == 2  # three workers and the runner
    texts = [
        tracker.download(state.run_id, f"failures/recovery_00{n}_lost_process.txt", tmp_path / str(n)).read_text()
        for n in (2, 3)
    ]
    assert "role 'trainer' was lost and Ray" in texts[0] and "role 'learner' was lost and Ray" in texts[1]

    # A loss the failure is about, or one reported before it, is not recorded a second time.
    attempt = Attempt(state, RunnerlessGroup(stateful={"trainer": 2}), phase="running", round_index=1)
    trainer_lost = Failure(
        LOST_PROCESS, "RoleWorkerLost: trainer", "detail", "sig2", recovered=tuple(reported), role="trainer"
    )
    assert scheduler._failed(attempt, trainer_lost) == "retry"
    assert state.recovered == 4 and state.lost_left == 0


@pytest.mark.parametrize("closing", ["after its last round", "restored after its last round"])
def test_a_stateful_loss_no_call_tripped_over_is_recorded_when_the_trial_finishes(tmp_path, closing):
    """A stateful worker lost between calls whose first call after it was its state loader (a restore handed it its
    state) trips nothing, so the runner reports nothing; Ray's table still counts the restart. A trial that then
    finishes records it, and it spends the budget, as it would have had the attempt failed."""
    from orchestrator.scheduler import Attempt
    from workers.methods import RoundReport

    tracker, scheduler, state = started_toy_trial(tmp_path, "loader_first", lost_left=3)
    group = RunnerlessGroup(stateful={"trainer": 1})
    if closing == "after its last round":
        attempt = Attempt(state, group, phase="running", round_index=3)
        last = RoundReport(3, {"loss": 1.0}, step=3, done=True, summary={"final_loss": 1.0})
        assert scheduler._advance(attempt, (last, b"state", [])) == "finished"
        assert tracker.summarised_round(state.run_id) == 3  # what a resume after a lost close goes by
    else:  # the driver died after the last checkpoint: the resume restores it and only closes the run
        attempt = Attempt(state, group, phase="restoring", checkpoint_round=3)
        assert scheduler._advance(attempt, 4) == "finished"
    assert history(tracker, state.run_id, "recovered/lost_process") == [(1, 1.0)]
    assert state.lost_left == 2
    text = tracker.download(state.run_id, "failures/recovery_001_lost_process.txt", tmp_path / "r").read_text()
    assert "role 'trainer' was lost and Ray restarted it" in text


@pytest.mark.parametrize(
    "summarised, restored, closes",
    [(1, 2, True), (3, 3, False), (None, 4, True), (None, 3, False)],
    ids=["ended early, checkpointed", "last checkpoint missing", "planned end", "planned end, checkpoint missing"],
)
def test_a_restore_only_closes_a_run_whose_checkpoint_follows_its_summarised_last_round(
    tmp_path, summarised, restored, closes
):
    """The summary names the round that ended the trial: a program that ended before its planned rounds (round 1 of
    4) and whose driver died as it closed is closed on resume, not run on; a summary of a later round than the
    restored checkpoint means the last checkpoint was lost, and that round runs again. Without a summary, the
    planned rounds decide."""
    from orchestrator.scheduler import Attempt

    tracker, scheduler, state = started_toy_trial(tmp_path, "summarised", lost_left=3)
    if summarised is not None:
        tracker.record_summary(state.run_id, {"final_loss": 1.0}, last_round=summarised)
    attempt = Attempt(state, RunnerlessGroup(), phase="restoring", checkpoint_round=restored - 1)
    outcome = scheduler._advance(attempt, restored)
    assert (outcome == "finished") is closes
    if not closes:
        assert attempt.phase == "running" and attempt.round_index == restored


def test_a_stateful_loss_is_recorded_once_whether_rays_table_or_the_runner_tells_first(tmp_path):
    """Both count the same restarts, each possibly late: a loss read from the table at a round's end is not recorded
    again when the runner trips over it in the next round, and one the runner reports before the table shows it is
    not recorded again when the table catches up."""
    from orchestrator.failures import LOST_PROCESS, Failure
    from orchestrator.scheduler import Attempt
    from workers.methods import RoleWorkerLost, RoundReport

    tracker, scheduler, state = started_toy_trial(tmp_path, "told_first", lost_left=5)
    group = RunnerlessGroup(stateful={"trainer": 1})  # lost after its last call of round 0
    attempt = Attempt(state, group, phase="running", round_index=0)
    scheduler._advance(attempt, (RoundReport(0, {"loss": 1.0}, step=0), b"state", []))
    assert state.recovered == 1
    reported = [str(RoleWorkerLost("trainer", "restarted without its state"))]
    scheduler._advance(attempt, (RoundReport(1, {"loss": 1.0}, step=1), b"state", reported))  # round 1 tripped
    assert state.recovered == 1
    group.stateful = {"trainer": 1}  # a second loss, reported before the table shows it
    scheduler._advance(attempt, (RoundReport(2, {"loss": 1.0}, step=2), b"state", reported))
    assert state.recovered == 2
    group.stateful = {"trainer": 2}  # the table catches up; then the runner is lost
    runner_lost = Failure(LOST_PROCESS, "ActorDiedError: the runner", "detail", "sig")
    assert scheduler._failed(attempt, runner_lost) == "retry"
    assert history(tracker, state.run_id, "recovered/lost_process") == [(1, 1.0), (2, 1.0)]
    assert state.lost_left == 2  # two workers and the runner


def test_a_failure_about_a_loss_rays_table_told_of_first_does_not_charge_it_again(tmp_path):
    """A trainer lost between rounds is read from the table at round 0's end (a recovery, charged); round 1 trips
    over it and its restore fails, so the attempt fails on that same loss: retried, not charged a second time. A
    second trainer loss the table counts by then is charged, once."""
    from orchestrator.failures import LOST_PROCESS, Failure
    from orchestrator.scheduler import Attempt
    from workers.methods import RoundReport

    tracker, scheduler, state = started_toy_trial(tmp_path, "charged_first", lost_left=1)
    group = RunnerlessGroup(stateful={"trainer": 1})
    attempt = Attempt(state, group, phase="running", round_index=0)
    scheduler._advance(attempt, (RoundReport(0, {"loss": 1.0}, step=0), b"state", []))
    assert state.lost_left == 0
    restore_failed = Failure(LOST_PROCESS, "RoleWorkerLost: trainer", "detail", "sig", role="trainer")
    assert scheduler._failed(attempt, restore_failed) == "retry" and state.lost_left == 0

    tracker, scheduler, state = started_toy_trial(tmp_path, "charged_twice", lost_left=3)
    group = RunnerlessGroup(stateful={"trainer": 1})
    attempt = Attempt(state, group, phase="running", round_index=0)
    scheduler._advance(attempt, (RoundReport(0, {"loss": 1.0}, step=0), b"state", []))
    group.stateful = {"trainer": 2}
    assert scheduler._failed(attempt, restore_failed) == "retry"
    assert state.lost_left == 1 and state.recovered == 2  # two losses, two charges; the failure is the first's


class LaggingTableGroup(RunnerlessGroup):
    """A group in whose actor table a second trainer loss shows up ``lag`` seconds after it is made: the GCS
    counts a killed worker only once its node has told it."""

    def __init__(self, lag: float):
        super().__init__(stateful={"trainer": 0})
        self.counted_from = time.monotonic() + lag

    def stateful_restarts(self) -> dict[str, int]:
        return {"trainer": 1 if time.monotonic() >= self.counted_from else 0}


@pytest.mark.parametrize("ending", ["failure", "ctrl-c"])
def test_a_loss_the_actor_table_counts_moments_after_the_attempt_ends_is_recorded(tmp_path, ending):
    """A trainer killed just before the attempt ends (beside the runner's loss, or with a Ctrl-C) is in Ray's
    table only some milliseconds later; the table is read once, before the actors go, so that read waits for it."""
    from orchestrator.failures import LOST_PROCESS, Failure
    from orchestrator.scheduler import TABLE_SETTLE_SECONDS, Attempt

    tracker, scheduler, state = started_toy_trial(tmp_path, f"lagging_{ending[:4]}", lost_left=3)
    attempt = Attempt(state, LaggingTableGroup(lag=TABLE_SETTLE_SECONDS / 2), phase="running")
    if ending == "failure":
        runner_lost = Failure(LOST_PROCESS, "ActorDiedError: the runner", "detail", "sig")
        assert scheduler._failed(attempt, runner_lost) == "retry"
    else:
        state.launched_here = True
        scheduler._active, scheduler._states = [attempt], [state]
        scheduler._abort(tracker.find_sweep_run(f"lagging_{ending[:4]}", "r").run_id, "interrupted", "Ctrl-C", "")
    assert history(tracker, state.run_id, "recovered/lost_process") == [(1, 1.0)]


def test_recoveries_in_place_past_the_budget_stop_the_trial_after_the_round(tmp_path):
    """Ray restarts each worker up to the whole budget, so one round can recover more than is left: the trial
    stops once its round is logged and checkpointed, FAILED with the count, not after a later loss."""
    from orchestrator.scheduler import Attempt
    from workers.methods import RoundReport

    tracker, scheduler, state = started_toy_trial(tmp_path, "overspent", lost_left=1)
    group = RunnerlessGroup({"relabel": 0})
    attempt = Attempt(state, group, phase="running", round_index=0)
    assert scheduler._advance(attempt, (RoundReport(0, {"loss": 1.0}, step=0), b"state", [])) is None
    group.restarts["relabel"] = 2
    assert scheduler._advance(attempt, (RoundReport(1, {"loss": 1.0}, step=1), b"state", [])) == "failed"
    run = tracker.client.get_run(state.run_id)
    assert run.info.status == "FAILED" and "more than max_lost_processes" in run.data.tags["icemlab.error"]
    assert [s for s, _ in history(tracker, state.run_id, "icemlab.round")] == [0, 1]  # the round is kept
    assert history(tracker, state.run_id, "recovered/lost_process") == [(1, 1.0), (2, 1.0)]


def test_the_next_round_starts_without_the_finished_rounds_progress(tmp_path):
    """Between a round's end and the next poll of the runner, the ETA must not count the finished round's fraction
    (about 1) as progress of the next one: for an MBRL frozen row that is hours early. And a round's checkpoint
    written anew is no longer the refused one of an earlier attempt."""
    from orchestrator.scheduler import Attempt, TrialState, time_to_go
    from workers.methods import RoundReport

    sweep = toy_sweep(tmp_path, "fraction")
    tracker = Tracker(default_tracking_uri(tmp_path))
    scheduler = SweepScheduler(load_sweep(sweep), tracker)
    parent = tracker.start_sweep("fraction", "fraction", "hash", sweep.read_text(), {}, "dev")
    state = TrialState(load_sweep(sweep).trials[0], 3, round_work=(1.0, 1.0, 13.0), rounds_done=1)
    state.run_id = tracker.start_trial(parent, state.trial.key, "trial", {"seed": 0}, {})
    state.bad_checkpoints = {1}  # round 1's checkpoint was refused in an earlier attempt
    finished_round = {"fraction": 1.0, "text": "step 10"}
    attempt = Attempt(state, RunnerlessGroup(), phase="running", round_index=1, progress=finished_round)
    scheduler._advance(attempt, (RoundReport(1, {"loss": 1.0}, step=1), b"state", []))
    assert attempt.round_index == 2 and attempt.progress == {}
    assert state.bad_checkpoints == set()  # written anew: a later restore may use it
    # The lost attempt's last fraction is not the restored one's.
    restoring = Attempt(state, RunnerlessGroup(), phase="restoring", checkpoint_round=1, progress={"fraction": 0.9})
    assert scheduler._shown_progress(restoring)["round"] == 1  # the checkpoint's round, not the new attempt's 0
    scheduler._advance(restoring, 2)
    assert restoring.phase == "running" and restoring.round_index == 2 and restoring.progress == {}
    # One unit of work in this session's 60 s: the frozen row's 13 units are 13 minutes away.
    assert time_to_go([state], {id(state): attempt.progress.get("fraction", 0.0)}, 1.0, 60.0) == 13 * 60.0


def test_a_launched_trial_is_this_drivers_to_close(tmp_path, monkeypatch):
    """Launching an attempt marks the trial as this driver's: Ctrl-C or a driver error then closes its run."""
    import orchestrator.scheduler as scheduler_module
    from orchestrator.scheduler import TrialState

    class Unplaced:
        def __init__(self, *args):
            pass

        def ready(self):
            return "ref"

    monkeypatch.setattr(scheduler_module, "TrialGroup", Unplaced)
    sweep = toy_sweep(tmp_path, "launch")
    tracker = Tracker(default_tracking_uri(tmp_path))
    scheduler = SweepScheduler(load_sweep(sweep), tracker)
    scheduler._parent_id = tracker.start_sweep("launch", "launch", "hash", sweep.read_text(), {}, "dev")
    scheduler._threads = 1
    state = TrialState(load_sweep(sweep).trials[0], 4)
    assert not state.launched_here
    attempt = scheduler._launch(state)
    assert state.launched_here and attempt.phase == "placing" and state.run_id is not None


def test_a_recovery_whose_file_a_dying_driver_never_wrote_still_numbers_the_next_one(tmp_path):
    """The metric of recovery 2 is written, the driver dies before its file: the resume numbers on from 3, not
    from 2 again (which would log the metric's step 2 twice)."""
    tracker, _, state = started_toy_trial(tmp_path, "half_recorded")
    tracker.record_recovery(state.run_id, 1, "lost_process", "first")
    log_text = tracker.client.log_text

    def dies(*args, **kwargs):
        raise DriverDied()

    tracker.client.log_text = dies
    with pytest.raises(DriverDied):
        tracker.record_recovery(state.run_id, 2, "lost_process", "second")
    tracker.client.log_text = log_text
    assert tracker.recoveries(state.run_id) == 2


def test_a_resumed_trials_recoveries_are_numbered_on(tmp_path, local_ray):
    """A recovery in a resumed session is the trial's second, not a second first: both records stay."""
    sweep = toy_sweep(tmp_path, "renumber", train_seconds=1.0)
    uri = default_tracking_uri(tmp_path)
    dying = DyingTracker(uri, "log_round", lambda run_id, index, *_, **__: index == 1, DriverDied())
    with pytest.raises(DriverDied):
        SweepScheduler(load_sweep(sweep), dying).run()
    (child,) = sweep_runs(uri, "renumber")[1]
    dying.record_recovery(child.run_id, 1, "lost_process", "the first session's trainer died")

    tracker = Tracker(uri)
    scheduler = SweepScheduler(load_sweep(sweep), tracker, resume=True)

    def kill_the_trainer_in_training():
        def trainer():
            active = scheduler._active
            if active and active[0].phase == "running":
                return active[0].group.workers["trainer"][0]
            return None

        worker = wait_for(trainer, timeout=120, interval=0.05, what="a running round")
        time.sleep(0.5)  # inside the training call (it sleeps 1 s first)
        os.kill(ray.get(worker.pid.remote()), signal.SIGKILL)

    killer = threading.Thread(target=kill_the_trainer_in_training, daemon=True)
    killer.start()
    assert scheduler.run().finished == 1
    killer.join(timeout=5)
    assert not killer.is_alive()
    (child,) = sweep_runs(uri, "renumber")[1]
    assert history(tracker, child.run_id, "recovered/lost_process") == [(1, 1.0), (2, 1.0)]
    files = sorted(tracker.list_files(child.run_id, "failures"))
    assert [f.rsplit("/", 1)[-1] for f in files if "recovery" in f] == [
        "recovery_001_lost_process.txt",
        "recovery_002_lost_process.txt",
    ]


@pytest.mark.parametrize("method", ["toy", pytest.param("mpc", marks=pytest.mark.slow)])
def test_driver_sigkill_then_resume_continues_from_the_last_round(tmp_path, method):
    if method == "toy":
        sweep = toy_sweep(tmp_path, "crash", seeds=(0, 1), rounds=4, train_seconds=0.3)
    else:
        base = {"planner": {"budget": 50, "horizon": 10}, "max_steps": 24, "round_steps": 4}
        sweep = write_sweep(tmp_path, "crash", seeds=[0, 1], base=base)
    uri = default_tracking_uri(tmp_path)
    driver = start_cli("run", str(sweep), "--max-concurrent", "1", "--quiet", cwd=tmp_path)
    tracker = Tracker(uri)
    try:

        def mid_trial():
            _, children = sweep_runs(uri, "crash")
            running = [c for c in children if c.status == RUNNING]
            return running and len(tracker.logged_rounds(running[0].run_id)) >= 2

        wait_for(mid_trial, timeout=180, what="a trial two rounds in")
        os.kill(driver.pid, signal.SIGKILL)  # the driver only; its Ray processes are orphaned
        driver.wait(timeout=30)
    finally:
        kill_group(driver)  # clean up the orphaned local Ray of the killed driver

    _, before = sweep_runs(uri, "crash")
    interrupted = {c.trial_key: c.run_id for c in before if c.status == RUNNING}
    assert len(interrupted) == 1

    result = cli("run", str(sweep), "--resume", "--quiet", cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    parent, after = sweep_runs(uri, "crash")
    assert parent.status == FINISHED
    assert sorted(c.trial_key for c in after) == sorted(t.key for t in load_sweep(sweep).trials)  # one run each
    assert all(c.status == FINISHED for c in after)
    resumed = next(c for c in after if c.trial_key in interrupted)
    assert resumed.run_id == interrupted[resumed.trial_key] and resumed.attempts == 2  # the same run, continued
    # The lost driver is a failure in MLflow: of the attempt it ran, in the trial it left RUNNING and the sweep.
    for run_id, others in ((resumed.run_id, [c for c in after if c is not resumed]), (parent.run_id, [])):
        assert tracker.list_files(run_id, "failures") == ["failures/attempt_001_driver_lost.txt"]
        assert history(tracker, run_id, "failures/driver_lost") == [(1, 1.0)]
        for other in others:
            assert not tracker.list_files(other.run_id, "failures")
    lost = tracker.download(resumed.run_id, "failures/attempt_001_driver_lost.txt", tmp_path / "lost").read_text()
    assert f"the driver (pid {driver.pid} on " in lost and "without closing the run" in lost
    rounds = METHODS[method].planned_rounds(load_sweep(sweep).trials[0].config.spec())
    key = "loss" if method == "toy" else "step/reward"
    for child in after:
        assert [s for s, _ in history(tracker, child.run_id, "icemlab.round")] == list(range(rounds))
        steps = [s for s, _ in history(tracker, child.run_id, key)]
        assert not [s for s, n in Counter(steps).items() if n > 1]  # no metric step logged twice
    # The resumed trial ends exactly as an uninterrupted run with the same seed.
    trial = next(t for t in load_sweep(sweep).trials if t.key == resumed.trial_key)
    expected = run_locally(METHODS[method], trial.config.spec())
    if method == "toy":
        assert [v for _, v in history(tracker, resumed.run_id, "loss")] == [r.metrics["loss"] for r in expected]
    else:
        assert resumed.metrics["mean_return"] == expected[-1].summary["mean_return"]
    assert "already done" in result.stderr


@pytest.mark.slow  # a whole sweep through the CLI; the default suite keeps the Ray-free checks
def test_a_trial_group_is_placed_all_at_once_or_not_at_all(tmp_path, local_ray):
    """The toy trial needs 2 CPUs (runner + trainer): with one CPU taken, nothing of it starts."""
    spec = load_sweep(toy_sweep(tmp_path, "placing")).trials[0].config.spec()
    blocker = ray.remote(num_cpus=1)(toy_method.ToyTrainer).remote(0)
    ray.get(blocker.pid.remote())
    group = TrialGroup(spec, 1, {}, max_restarts=0)
    try:
        assert group.cpus == 2
        ready, _ = ray.wait([group.ready()], timeout=3)
        assert not ready  # one bundle could be reserved, but the group waits whole
        ray.kill(blocker)
        ray.get(group.ready(), timeout=30)
        runner = group.start()
        report, _, _ = ray.get(runner.run_round.remote(0), timeout=60)
        assert report.metrics["weights_version"] == 1
    finally:
        group.teardown()


def test_actors_that_reserve_nothing_share_the_first_bundle():
    roles = [RoleSpec("simulation", object, 2, 1), RoleSpec("trainer", object, 1, 0), RoleSpec("gpu", object, 1, 0, gpus=1)]
    layout = bundle_layout(0.5, roles)
    assert layout.bundles == [{"CPU": 0.5}, {"CPU": 1.0}, {"CPU": 1.0}, {"CPU": 0.0, "GPU": 1.0}]
    assert layout.runner == 0 and layout.roles == {"simulation": [1, 2], "trainer": [0], "gpu": [3]}
    assert bundle_layout(0, roles[:2]).roles == {"simulation": [0, 1], "trainer": [0]}
    with pytest.raises(ValueError, match="nothing to place"):
        bundle_layout(0, [RoleSpec("trainer", object, 1, 0)])


def test_zero_cpu_actors_never_land_in_a_gpu_only_bundle():
    roles = [RoleSpec("gpu", object, 1, 0, gpus=1), RoleSpec("relabel", object, 1, 2), RoleSpec("trainer", object, 1, 0)]
    layout = bundle_layout(0, roles)
    assert layout.bundles == [{"CPU": 0.0, "GPU": 1.0}, {"CPU": 2.0}]
    assert layout.runner == 1 and layout.roles == {"gpu": [0], "relabel": [1], "trainer": [1]}


@pytest.mark.parametrize(
    "bundles, nodes, fit",
    [
        ([{"CPU": 1}], [2], 2),
        ([{"CPU": 2}], [1, 1], 0),  # a bundle lives on one node
        ([{"CPU": 1}, {"CPU": 1}], [1, 1], 1),  # one group spread over two nodes
        ([{"CPU": 2}, {"CPU": 0.5}], [2, 1, 1], 1),
        ([{"CPU": 0.0, "GPU": 1.0}, {"CPU": 1}], [4], 4),
    ],
)
def test_groups_that_fit_count_whole_groups_placed_bundle_by_bundle(bundles, nodes, fit):
    assert groups_that_fit(bundles, nodes, limit=4) == fit


def test_a_cluster_of_one_cpu_nodes_gets_one_cpu_units_not_a_hanging_placement(tmp_path):
    """Two 1-CPU nodes hold 2 CPUs, but no bundle of 2: units of one CPU, two trials at once."""
    loaded = load_sweep(write_sweep(tmp_path, "nodes", seeds=[0, 1]))
    assert SweepScheduler(loaded, tracker=None, max_concurrent=1).layout(2, 2) == (2, 1)
    assert SweepScheduler(loaded, tracker=None, max_concurrent=1).layout([1, 1], 2) == (1, 1)
    assert SweepScheduler(loaded, tracker=None).layout([1, 1], 2) == (1, 2)
    pinned = load_sweep(write_sweep(tmp_path, "pinned", resources={"threads_per_worker": 2}))
    assert SweepScheduler(pinned, tracker=None).layout(2, 1) == (2, 1)
    with pytest.raises(ResourceError, match="bundles of 2 CPUs, each on one node.*nodes have 1, 1 CPUs"):
        SweepScheduler(pinned, tracker=None).layout([1, 1], 1)


def test_the_layout_holds_the_largest_trial_of_the_sweep_not_the_first(tmp_path):
    """napsp's Pick&Place sweep begins with Sparse+HER (no distance trainer) and goes on to variants that hold
    more CPUs: one trial at a time on four CPUs, every trial's group must fit, or the larger ones never start."""
    import yaml

    shipped = Path(__file__).resolve().parents[1] / "sweeps" / "paper" / "napsp_fetch_pick_place.yaml"
    sweep = yaml.safe_load(shipped.read_text())
    del sweep["resources"]["threads_per_worker"]  # the thread count is the layout's to choose
    path = tmp_path / "napsp.yaml"
    path.write_text(yaml.safe_dump(sweep, sort_keys=False))
    loaded = load_sweep(path)
    scheduler = SweepScheduler(loaded, Tracker(default_tracking_uri(tmp_path)), max_concurrent=1)
    program = METHODS["napsp"]
    sizes = {program.runner_cpus(t.config.spec(), 1)
             + sum(r.cpus * r.count for r in program.roles_for(t.config.spec(), 1, {})) for t in loaded.trials}
    assert len(sizes) > 1  # the premise: groups of different sizes, the first not the largest
    threads, concurrent = scheduler.layout(4, len(loaded.trials))
    assert concurrent == 1
    for trial in loaded.trials:
        spec = trial.config.spec()
        roles = [r for r in program.roles_for(spec, threads, {}) if r.count]
        group = bundle_layout(program.runner_cpus(spec, threads), roles).bundles
        assert sum(b["CPU"] for b in group) <= 4, (trial.variant, threads)


def test_a_trial_larger_than_the_cluster_is_refused_before_anything_runs(tmp_path, local_ray):
    sweep = write_sweep(tmp_path, "too_big", resources={"simulation_workers": 3, "threads_per_worker": 1})
    tracker = Tracker(default_tracking_uri(tmp_path))
    with pytest.raises(ResourceError, match="needs 3 CPUs"):
        SweepScheduler(load_sweep(sweep), tracker).run()
    assert tracker.find_sweep_run("too_big", "too_big") is None


@pytest.mark.parametrize(
    "stop, code",
    [
        ("ctrl_c", 130),  # SIGINT to the process group: what a terminal sends on Ctrl-C
        ("sigterm", 143),  # SIGTERM to the driver alone: kill, ray job stop, a pod's eviction
    ],
)
def test_ctrl_c_or_sigterm_stops_cleanly_and_marks_unfinished_runs_killed(tmp_path, stop, code):
    sweep = write_sweep(
        tmp_path, "interrupt", seeds=[0, 1, 2], base={"planner": {"budget": 300, "horizon": 30}, "max_steps": 600}
    )
    uri = default_tracking_uri(tmp_path)
    driver = start_cli("run", str(sweep), "--max-concurrent", "1", cwd=tmp_path)
    try:
        wait_for(
            lambda: any(c.status == RUNNING for c in sweep_runs(uri, "interrupt")[1]) or driver.poll() is not None,
            timeout=180,
            what="a running trial",
        )
        assert driver.poll() is None, driver.stdout.read()
        second = cli("run", str(sweep), "--resume", cwd=tmp_path)  # a second driver would run the trials twice
        assert second.returncode == 2 and f"still being run by the driver with pid {driver.pid}" in second.stderr
        assert "kill -INT" in second.stderr and sweep_runs(uri, "interrupt")[0].status == RUNNING
        # The second driver took seconds: the signal must land while a trial runs, not between two trials.
        wait_for(lambda: any(c.status == RUNNING for c in sweep_runs(uri, "interrupt")[1]), timeout=60,
                 what="a running trial")  # fmt: skip
        time.sleep(1.0)
        if stop == "ctrl_c":
            os.killpg(driver.pid, signal.SIGINT)
        else:
            os.kill(driver.pid, signal.SIGTERM)
        output, _ = driver.communicate(timeout=120)
    finally:
        kill_group(driver)
    assert driver.returncode == code, output
    said = "Ctrl-C" if stop == "ctrl_c" else "SIGTERM"
    assert f"interrupted ({said})" in output and "--resume" in output  # tells the user how to continue
    parent, children = sweep_runs(uri, "interrupt")
    assert parent.status == KILLED
    assert children and not [c for c in children if c.status == RUNNING]
    killed = [c for c in children if c.status == KILLED]
    assert killed and {c.error for c in killed} == {f"interrupted ({said})"}


def test_each_driver_error_of_a_sweep_is_kept_and_notes_of_one_millisecond_are_too(tmp_path, monkeypatch):
    """A second session's driver error is recorded beside the first one, not over it; two notes written in the
    same millisecond are two files."""
    import orchestrator.tracking as tracking

    tracker = Tracker(default_tracking_uri(tmp_path))
    parent = tracker.start_sweep("errors", "errors", "hash", "name: errors\n", {}, "dev")
    tracker.record_sweep_failure(parent, "driver_error", "first", "first session")
    tracker.record_sweep_failure(parent, "driver_error", "second", "second session")
    files = sorted(tracker.list_files(parent, "failures"))
    assert files == ["failures/attempt_001_driver_error.txt", "failures/attempt_002_driver_error.txt"]
    texts = [tracker.download(parent, f, tmp_path / f"copy_{i}").read_text() for i, f in enumerate(files)]
    assert "first session" in texts[0] and "second session" in texts[1]

    monkeypatch.setattr(tracking, "_now_ms", lambda: 1_700_000_000_000)
    tracker.note(parent, "one")
    tracker.note(parent, "two")
    assert len(tracker.list_files(parent, "notes")) == 2


def test_a_step_logged_twice_reads_as_its_latest_value(tmp_path):
    """A round re-run after a crash may log a step again: the curves and per-episode tests take the latest."""
    from mlflow.entities import Metric

    tracker = Tracker(default_tracking_uri(tmp_path))
    parent = tracker.start_sweep("twice", "twice", "hash", "name: twice\n", {}, "dev")
    run = tracker.start_trial(parent, "key", "trial", {"seed": 0}, {})
    for timestamp, step, value in ((1000, 0, 1.0), (2000, 1, 5.0), (3000, 1, 3.0)):
        tracker.client.log_batch(run, metrics=[Metric("episode_return", value, timestamp, step)])
    (history,) = tracker.histories([run], ["episode_return"])[run].values()
    assert dict(history) == {0: 1.0, 1: 3.0} and [step for step, _ in history] == [0, 1, 1]


def test_the_embedded_store_is_created_under_its_lock(tmp_path, monkeypatch):
    """MLflow creates its tables as soon as a client is constructed: two processes opening a fresh store at once
    (a test or `icemlab status` polling a starting driver) made one fail with "table ... already exists"."""
    import fcntl

    import orchestrator.tracking as tracking

    constructed = []

    class Client(tracking.MlflowClient):
        def __init__(self, *args, **kwargs):
            with open(tmp_path / "mlflow.db.lock", "w") as probe:
                try:
                    fcntl.flock(probe, fcntl.LOCK_EX | fcntl.LOCK_NB)
                    constructed.append("unlocked")
                except BlockingIOError:
                    constructed.append("locked")
            super().__init__(*args, **kwargs)

    monkeypatch.setattr(tracking, "MlflowClient", Client)
    Tracker(default_tracking_uri(tmp_path))
    assert constructed == ["locked"]
