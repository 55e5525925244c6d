"""APEX on the real service: Ray actors for its roles, MLflow, faults.

* the shipped smoke sweep runs end to end through the CLI (both roles, two rounds, checkpoints);
* a RelabelWorker killed with SIGKILL in the middle of a relabeling call is restarted and the call
  retried: the trial ends exactly as an undisturbed one (no label lost, none twice);
* a driver killed with SIGKILL mid-trial is continued by ``--resume`` from the last completed
  iteration (marker slow).
"""

from __future__ import annotations

import os
import signal
import threading
import time
from collections import Counter
from pathlib import Path

import pytest
import ray
import yaml
from helpers import cli, kill_group, start_cli, sweep_runs, wait_for

from orchestrator.placement import bundle_layout
from orchestrator.scheduler import SweepScheduler
from orchestrator.sweep import load_sweep
from orchestrator.tracking import FINISHED, RUNNING, Tracker, default_tracking_uri
from workers.methods import METHODS, run_locally

ROOT = Path(__file__).resolve().parents[1]
TESTS = str(ROOT / "tests")
# Ray's worker processes and CLI subprocesses import this checkout (an installed icemlab would shadow it).
os.environ["PYTHONPATH"] = os.pathsep.join(
    dict.fromkeys([str(ROOT), TESTS, *filter(None, os.environ.get("PYTHONPATH", "").split(os.pathsep))])
)
ENV = {"PYTHONPATH": os.environ["PYTHONPATH"]}

COMPARED = ("expert_return", "policy_return", "loss/first_training", "loss/second_training", "lambda/relabel_mean",
            "dataset/relabeled_steps", "dataset/steps", "weights_version")  # fmt: skip


@pytest.fixture(scope="module")
def local_ray():
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    yield
    ray.shutdown()


def apex_sweep(directory: Path, name: str, seeds=(0,), **base) -> Path:
    settings = {
        "planner": {"budget": 45, "horizon": 10},
        "iterations": 2,
        "rollouts": 2,
        "window": 4,
        "episode_steps": 30,
        "relabel_chunk": 5,
        "policy": {"gradient_steps": 20, "batch_size": 128},
    } | base
    sweep = {"name": name, "task": "point_reach", "method": "apex", "base": settings, "seeds": list(seeds)}
    sweep["resources"] = {"workers": {"relabel": 1}}
    path = directory / f"{name}.yaml"
    path.write_text(yaml.safe_dump(sweep, sort_keys=False))
    return path


def test_on_two_cores_the_relabel_worker_gets_both_and_the_trainer_shares_its_bundle(tmp_path):
    """The phases of an APEX iteration alternate, so the runner and the trainer reserve no CPUs: on a 2-CPU
    cluster one trial's relabel worker plans with both CPUs (or two trials run at once, one CPU each), and
    the runner and trainer run in that worker's bundle."""
    loaded = load_sweep(apex_sweep(tmp_path, "layout", seeds=(0, 1)))
    tracker = Tracker(default_tracking_uri(tmp_path))
    assert SweepScheduler(loaded, tracker, max_concurrent=1).layout(2, 2) == (2, 1)
    assert SweepScheduler(loaded, tracker).layout(2, 2) == (1, 2)
    spec = loaded.trials[0].config.spec()
    roles = METHODS["apex"].roles_for(spec, 2, {"relabel": 1})
    layout = bundle_layout(METHODS["apex"].runner_cpus(spec, 2), roles)
    assert layout.bundles == [{"CPU": 2.0}]
    assert layout.runner == 0 and layout.roles == {"relabel": [0], "trainer": [0]}
    assert next(role for role in roles if role.name == "trainer").kwargs["cpus"] == 2
    # With more relabel workers the trainer still shares the first one's bundle, of the same size.
    roles = METHODS["apex"].roles_for(spec, 2, {"relabel": 3})
    layout = bundle_layout(METHODS["apex"].runner_cpus(spec, 2), roles)
    assert layout.bundles == [{"CPU": 2.0}] * 3 and layout.roles == {"relabel": [0, 1, 2], "trainer": [0]}


def history(tracker: Tracker, run_id: str, key: str) -> list[tuple[int, float]]:
    return sorted(tracker.metric_history(run_id, key))


@pytest.mark.slow  # a whole sweep through the CLI; the default suite keeps the Ray-free checks
def test_smoke_sweep_runs_every_role_through_the_cli(tmp_path):
    started = time.monotonic()
    result = cli("run", str(ROOT / "sweeps" / "smoke" / "apex.yaml"), "--quiet", cwd=tmp_path, env=ENV, timeout=240)
    seconds = time.monotonic() - started
    assert result.returncode == 0, result.stderr
    assert "point_reach" in result.stdout
    tracker = Tracker(default_tracking_uri(tmp_path))
    parent, (child,) = sweep_runs(tracker.uri, "apex_smoke")
    assert parent.status == FINISHED and child.status == FINISHED and child.params["method"] == "apex"
    assert [s for s, _ in history(tracker, child.run_id, "icemlab.round")] == [0, 1]
    assert [v for _, v in history(tracker, child.run_id, "weights_version")] == [2, 4]  # the trainer role
    assert [v for _, v in history(tracker, child.run_id, "dataset/relabeled_steps")] == [50, 50]  # relabel role
    assert set(tracker.list_files(child.run_id, "policy")) == {"policy/policy_0000.npz", "policy/policy_0001.npz"}
    assert len(tracker.list_files(child.run_id, "checkpoints")) == 2
    assert "apex_curves.png" in tracker.list_files(child.run_id)
    assert child.metrics["policy_return"] < 0 and "evaluation_return" in child.metrics
    print(f"smoke sweep through the CLI: {seconds:.0f} s")


def relabel_processes() -> list[int]:
    """PIDs of RelabelWorker actors busy relabeling (Ray titles its worker processes ray::Class.method)."""
    found = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                title = (entry / "cmdline").read_bytes().split(b"\0")[0]
            except OSError:
                continue
            if title.startswith(b"ray::RelabelWorker.relabel"):
                found.append(int(entry.name))
    return found


@pytest.mark.slow
def test_killed_relabel_worker_loses_and_duplicates_no_labels(tmp_path, local_ray):
    """SIGKILL a RelabelWorker inside a relabeling call: Ray restarts it and retries the call, and the trial
    ends exactly as an undisturbed run (every label once: same datasets, same losses)."""
    sweep = apex_sweep(tmp_path, "relabel_kill", iterations=1, episode_steps=40, planner={"budget": 45, "horizon": 15})
    loaded = load_sweep(sweep)
    tracker = Tracker(default_tracking_uri(tmp_path))
    scheduler = SweepScheduler(loaded, tracker)
    killed = {}

    def kill_mid_relabeling():
        def relabeling():
            # A worker titled ray::RelabelWorker.relabel is inside a call; the phase's progress line may lag
            # behind it (it is polled), and on a busy machine a short phase may be over before the line says so.
            return relabel_processes() if scheduler._active else None

        (pid, *_) = wait_for(relabeling, timeout=180, interval=0.02, what="a relabeling call under way")
        os.kill(pid, signal.SIGKILL)
        killed.update(pid=pid, text=scheduler._active[0].progress.get("text"))

    killer = threading.Thread(target=kill_mid_relabeling, daemon=True)
    killer.start()
    outcome = scheduler.run()
    killer.join(timeout=5)
    assert killed, "no relabeling call was caught under way"
    assert (outcome.finished, outcome.failed) == (1, 0)
    _, (child,) = sweep_runs(tracker.uri, "relabel_kill")
    assert child.status == FINISHED and child.attempts == 1  # absorbed by the restart, not a trial retry
    assert child.metrics["recovered/lost_process"] >= 1.0  # ... and recorded, read from Ray's actor table
    assert child.metrics["dataset/relabeled_steps"] == 80  # 2 policy episodes x 40 states, each labelled once
    (undisturbed,) = run_locally(METHODS["apex"], loaded.trials[0].config.spec())
    assert {k: child.metrics[k] for k in COMPARED} == {k: undisturbed.metrics[k] for k in COMPARED}


def experiment_exists(database: Path, name: str) -> bool:
    """Whether the SQLite store has the experiment (read with sqlite3, without MLflow's migrations)."""
    import sqlite3

    if not database.exists():
        return False
    with sqlite3.connect(f"file:{database}?mode=ro", uri=True) as connection:
        return bool(connection.execute("SELECT count(*) FROM experiments WHERE name = ?", (name,)).fetchone()[0])


@pytest.mark.slow
def test_driver_sigkill_then_resume_continues_from_the_last_iteration(tmp_path):
    sweep = apex_sweep(tmp_path, "apex_crash", seeds=(0, 1), iterations=3)
    uri = default_tracking_uri(tmp_path)
    driver = start_cli("run", str(sweep), "--max-concurrent", "1", "--quiet", cwd=tmp_path, env=ENV)
    try:
        # Touch the store only once the driver has created it (two processes migrating one new SQLite
        # store at once can break the driver's migration).
        wait_for(lambda: experiment_exists(tmp_path / "mlflow.db", "apex_crash"), timeout=240, what="the store")
        tracker = Tracker(uri)

        def mid_trial():
            _, children = sweep_runs(uri, "apex_crash")
            running = [c for c in children if c.status == RUNNING]
            return running and len(tracker.logged_rounds(running[0].run_id)) >= 1

        wait_for(mid_trial, timeout=240, what="a trial one iteration in")
        os.kill(driver.pid, signal.SIGKILL)  # the driver only; its Ray processes are orphaned
        driver.wait(timeout=30)
    finally:
        kill_group(driver)  # clean up the orphaned local Ray of the killed driver

    _, before = sweep_runs(uri, "apex_crash")
    interrupted = {c.trial_key: c.run_id for c in before if c.status == RUNNING}
    assert len(interrupted) == 1
    done_before = len(tracker.logged_rounds(next(iter(interrupted.values()))))

    result = cli("run", str(sweep), "--resume", "--quiet", cwd=tmp_path, env=ENV, timeout=600)
    assert result.returncode == 0, result.stderr
    parent, after = sweep_runs(uri, "apex_crash")
    assert parent.status == FINISHED and all(c.status == FINISHED for c in after)
    assert sorted(c.trial_key for c in after) == sorted(t.key for t in load_sweep(sweep).trials)
    resumed = next(c for c in after if c.trial_key in interrupted)
    assert resumed.run_id == interrupted[resumed.trial_key] and resumed.attempts == 2
    for child in after:
        assert [s for s, _ in history(tracker, child.run_id, "icemlab.round")] == [0, 1, 2]
        steps = [s for s, _ in history(tracker, child.run_id, "policy_return")]
        assert not [s for s, n in Counter(steps).items() if n > 1]  # no iteration logged twice
    trial = next(t for t in load_sweep(sweep).trials if t.key == resumed.trial_key)
    expected = run_locally(METHODS["apex"], trial.config.spec())
    assert [v for _, v in history(tracker, resumed.run_id, "loss/second_training")] == [
        r.metrics["loss/second_training"] for r in expected
    ]
    assert [v for _, v in history(tracker, resumed.run_id, "weights_version")] == [2, 4, 6]
    assert done_before >= 1
