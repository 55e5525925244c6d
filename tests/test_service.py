"""The service end to end: real Ray, real MLflow (SQLite), real faults.

* a sweep through the CLI lands in MLflow as a parent run with one FINISHED
  child per trial, params, metrics and artifacts;
* a trial that raises ends FAILED with its error, is retried, and the sweep goes on;
* a SimulationWorker killed mid-episode is restarted and the episode completes
  with the same result as without the kill;
* a driver killed with SIGKILL loses nothing: ``--resume`` runs only the
  missing trials and each trial ends with exactly one FINISHED run;
* Ctrl-C stops the sweep and marks the unfinished runs KILLED.
"""

from __future__ import annotations

import os
import signal
import threading
import time

import faulty
import numpy as np
import pytest
import ray
from helpers import cli, kill_group, start_cli, sweep_runs, wait_for, write_sweep

from orchestrator.scheduler import SweepScheduler
from orchestrator.sweep import load_sweep
from orchestrator.tracking import FAILED, FINISHED, KILLED, RUNNING, Tracker, default_tracking_uri
from workers.actors import TrialRunner


@pytest.fixture(scope="module")
def local_ray():
    """One local Ray for the in-process scheduler tests of this module."""
    ray.cloudpickle.register_pickle_by_value(faulty)
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    yield
    ray.shutdown()


def current(children):
    """Child runs that are a trial's latest attempt."""
    return [c for c in children if not c.superseded]


def test_cli_sweep_lands_in_mlflow(tmp_path):
    sweep = write_sweep(
        tmp_path,
        "landing",
        base={"planner": {"budget": 50, "horizon": 10}, "max_steps": 8, "episodes": 2},
        parameters={"algorithm": {"values": ["icem", "cem_mpc"]}},
    )
    result = cli("run", str(sweep), "--quiet", cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    assert "point_reach" in result.stdout  # the summary table

    parent, children = sweep_runs(default_tracking_uri(tmp_path), "landing")
    assert parent.info.status == FINISHED
    assert {c.status for c in children} == {FINISHED} and len(children) == 2
    keys = {t.key for t in load_sweep(sweep).trials}
    assert {c.trial_key for c in children} == keys
    for child in children:
        assert child.params["task"] == "point_reach" and child.params["planner.budget"] == "50"
        assert child.tags["task"] == "point_reach" and child.tags["seed"] == "0"
        assert child.tags["algorithm"] in ("icem", "cem_mpc")
        assert np.isfinite(child.metrics["episode_return"]) and child.metrics["simulated_steps_per_second"] > 0
    tracker = Tracker(default_tracking_uri(tmp_path))
    steps = tracker.metric_history(children[0].run_id, "step/reward")
    assert sorted(s for s, _ in steps) == list(range(16))  # 2 episodes x 8 steps, counted across episodes
    episodes = tracker.metric_history(children[0].run_id, "episode_return")
    assert sorted(s for s, _ in episodes) == [0, 1]
    assert children[0].metrics["mean_return"] == pytest.approx(np.mean([v for _, v in episodes]))
    parent_files = {f.path for f in tracker.client.list_artifacts(parent.info.run_id)}
    assert {"sweep.yaml", "summary.csv", "summary.txt", "budget_curve.png"} <= parent_files
    episode_files = {f.path for f in tracker.client.list_artifacts(children[0].run_id, "episodes")}
    assert episode_files == {"episodes/episode_000.png", "episodes/episode_001.png"}


def test_failing_trial_is_marked_failed_and_the_sweep_goes_on(tmp_path, local_ray):
    sweep = write_sweep(tmp_path, "failing", seeds=[0, 1], retries=1)
    tracker = Tracker(default_tracking_uri(tmp_path))
    outcome = SweepScheduler(load_sweep(sweep), tracker, runner_class=faulty.FailingRunner).run()
    assert (outcome.finished, outcome.failed) == (1, 1)

    parent, children = sweep_runs(tracker.uri, "failing")
    assert parent.info.status == FINISHED and parent.data.tags["icemlab.failed_trials"] == "1"
    by_seed = {}
    for child in children:
        by_seed.setdefault(child.tags["seed"], []).append(child)
    assert [c.status for c in by_seed["0"]] == [FINISHED]
    failed_attempts = sorted(by_seed["1"], key=lambda c: c.tags["icemlab.attempt"])
    assert [c.status for c in failed_attempts] == [FAILED, FAILED]  # first try + one retry
    assert failed_attempts[0].superseded and not failed_attempts[1].superseded
    assert all("injected failure" in c.tags["icemlab.error"] for c in failed_attempts)


def test_killed_simulation_worker_is_restarted_and_the_episode_completes(tmp_path, local_ray):
    """SIGKILL the remote SimulationWorker mid-episode; the result equals an undisturbed run."""
    sweep = write_sweep(
        tmp_path,
        "worker_kill",
        task="halfcheetah_running",
        base={"planner": {"budget": 300, "horizon": 30}, "max_steps": 30},
        resources={"simulation_workers": 2, "threads_per_worker": 1},
    )
    loaded = load_sweep(sweep)
    tracker = Tracker(default_tracking_uri(tmp_path))
    scheduler = SweepScheduler(loaded, tracker)
    killed = {}

    def kill_worker_mid_episode():
        def running_at_step():
            active = getattr(scheduler, "_active", [])
            return active[0] if active and active[0].progress.get("step", 0) >= 3 else None

        active = wait_for(running_at_step, timeout=120, interval=0.05, what="the trial to reach step 3")
        pid = ray.get(active.workers[0].pid.remote())
        os.kill(pid, signal.SIGKILL)
        killed.update(pid=pid, step=active.progress["step"])

    killer = threading.Thread(target=kill_worker_mid_episode, daemon=True)
    killer.start()
    outcome = scheduler.run()
    killer.join(timeout=5)
    assert killed, "the worker was never killed"
    assert killed["step"] < 30  # mid-episode
    assert (outcome.finished, outcome.failed) == (1, 0)

    _, children = sweep_runs(tracker.uri, "worker_kill")
    (child,) = children
    assert child.status == FINISHED
    assert child.metrics["simulation_worker_restarts"] >= 1  # the failure is visible in MLflow
    # Costs are a pure function of state and actions, so the retried call changes nothing.
    trial = loaded.trials[0].config
    undisturbed = TrialRunner(trial.task, trial.planner, trial.seed, max_steps=trial.max_steps).run_episode(0)
    assert child.metrics["episode_return"] == pytest.approx(undisturbed.result.episode_return, abs=1e-9)


def test_driver_sigkill_then_resume_loses_and_duplicates_nothing(tmp_path):
    sweep = write_sweep(
        tmp_path, "crash", seeds=[0, 1, 2, 3], base={"planner": {"budget": 50, "horizon": 10}, "max_steps": 15}
    )
    uri = default_tracking_uri(tmp_path)
    driver = start_cli("run", str(sweep), "--max-concurrent", "1", "--quiet", cwd=tmp_path)
    try:

        def one_finished_one_running():
            _, children = sweep_runs(uri, "crash")
            statuses = [c.status for c in children]
            return statuses.count(FINISHED) >= 1 and RUNNING in statuses

        wait_for(one_finished_one_running, timeout=180, what="one finished and one running trial")
        os.kill(driver.pid, signal.SIGKILL)  # the driver only; its Ray processes are orphaned
        driver.wait(timeout=30)
    finally:
        kill_group(driver)  # clean up the orphaned local Ray of the killed driver

    _, before = sweep_runs(uri, "crash")
    finished_before = {c.trial_key: c.run_id for c in before if c.status == FINISHED}
    assert 1 <= len(finished_before) < 4
    assert any(c.status == RUNNING for c in before)  # left behind by the kill

    result = cli("run", str(sweep), "--resume", "--quiet", cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    parent, after = sweep_runs(uri, "crash")
    assert parent.info.status == FINISHED
    keys = {t.key for t in load_sweep(sweep).trials}
    latest = current(after)
    assert sorted(c.trial_key for c in latest) == sorted(keys)  # one current run per trial
    assert all(c.status == FINISHED for c in latest)
    assert sum(c.status == FINISHED for c in after) == len(keys)  # no trial finished twice
    assert not [c for c in after if c.status == RUNNING]
    # Finished trials were not run again; the interrupted attempt is closed and points onward.
    assert {c.trial_key: c.run_id for c in latest if c.trial_key in finished_before} == finished_before
    interrupted = [c for c in after if c.superseded]
    assert interrupted and all(c.status == KILLED for c in interrupted)
    assert "already done" in result.stderr


def test_ctrl_c_stops_cleanly_and_marks_unfinished_runs_killed(tmp_path):
    sweep = write_sweep(
        tmp_path, "interrupt", seeds=[0, 1, 2], base={"planner": {"budget": 300, "horizon": 30}, "max_steps": 200}
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
        time.sleep(1.0)
        os.killpg(driver.pid, signal.SIGINT)  # what a terminal sends on Ctrl-C
        output, _ = driver.communicate(timeout=120)
    finally:
        kill_group(driver)
    assert driver.returncode == 130, output
    assert "--resume" in output  # tells the user how to continue
    parent, children = sweep_runs(uri, "interrupt")
    assert parent.info.status == KILLED
    assert children and not [c for c in children if c.status == RUNNING]
    assert any(c.status == KILLED for c in children)
