"""napsp through the service: the smoke sweep via the CLI, a killed DistanceTrainer, a killed driver.

* ``sweeps/smoke/napsp.yaml`` runs end to end through ``icemlab run``: both
  roles, a checkpoint per round, figures, the summary (default suite);
* a DistanceTrainer killed mid-iteration costs the round in flight; the trial
  restarts from its last checkpoint (weights, sketches, buffer) and ends as an
  undisturbed run ends (slow);
* a driver killed with SIGKILL loses nothing: ``--resume`` continues from the
  last completed iteration, no iteration logged twice (slow).
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

from orchestrator.scheduler import SweepScheduler
from orchestrator.sweep import load_sweep
from orchestrator.tracking import FINISHED, RUNNING, Tracker, default_tracking_uri
from workers.methods import METHODS, run_locally

ROOT = Path(__file__).resolve().parents[1]
# The CLI subprocesses and Ray's workers import this checkout, not whatever icemlab is installed.
os.environ["PYTHONPATH"] = os.pathsep.join(
    dict.fromkeys([str(ROOT), *filter(None, os.environ.get("PYTHONPATH", "").split(os.pathsep))])
)

SMALL = {
    "episodes_per_iteration": 1,
    "eval_episodes": 1,
    "plot_every": 0,
    "learner": {"hidden": [32], "batch_size": 32, "updates_per_episode": 10},
    "distance": {
        "hidden": [32],
        "batch_size": 32,
        "temporal_updates_per_episode": 10,
        "triangular_updates_per_episode": 10,
    },
}


def napsp_sweep(directory: Path, name: str, seeds=(0,), **settings) -> Path:
    sweep = {
        "name": name,
        "task": "fetch_reach",
        "method": "napsp",
        "base": SMALL | settings,
        "seeds": list(seeds),
        "retries": 0,
        "resources": {"threads_per_worker": 1},
    }
    path = directory / f"{name}.yaml"
    path.write_text(yaml.safe_dump(sweep, sort_keys=False))
    return path


def history(tracker: Tracker, run_id: str, key: str) -> list[tuple[int, float]]:
    return sorted(tracker.metric_history(run_id, key))


@pytest.mark.slow  # a whole sweep through the CLI; the default suite keeps the Ray-free checks
def test_smoke_sweep_runs_through_the_cli(tmp_path):
    """sweeps/smoke/napsp.yaml: every round and role, checkpoints, figures and the summary land in MLflow."""
    smoke = ROOT / "sweeps" / "smoke" / "napsp.yaml"
    started = time.monotonic()
    result = cli("run", str(smoke), "--quiet", cwd=tmp_path, timeout=600)
    assert result.returncode == 0, result.stderr
    seconds = time.monotonic() - started
    parent, (child,) = sweep_runs(default_tracking_uri(tmp_path), "napsp_smoke")
    assert parent.status == FINISHED and child.status == FINISHED
    tracker = Tracker(default_tracking_uri(tmp_path))
    rounds = METHODS["napsp"].planned_rounds(load_sweep(smoke).trials[0].config.spec())
    assert rounds >= 2
    assert [s for s, _ in history(tracker, child.run_id, "icemlab.round")] == list(range(rounds))
    assert [v for _, v in history(tracker, child.run_id, "distance_weights_version")] == list(range(1, rounds + 1))
    for key in ("eval/success", "learner/critic_loss", "distance/temporal_loss", "distance/triangular_idle_fraction"):
        assert [s for s, _ in history(tracker, child.run_id, key)] == list(range(rounds)), key  # step = iteration
    assert "eval_success" in child.metrics and "episodes_to_success" in child.metrics
    assert len(tracker.list_files(child.run_id, "checkpoints")) >= 2
    assert len(tracker.list_files(child.run_id, "maze")) == 2  # heat maps and coverage
    assert "curves.png" in tracker.list_files(parent.run_id)
    print(f"smoke sweep: {seconds:.0f} s")


@pytest.fixture(scope="module")
def local_ray():
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    yield
    ray.shutdown()


@pytest.mark.slow
def test_killed_distance_trainer_resumes_from_its_checkpoint(tmp_path, local_ray):
    """SIGKILL the DistanceTrainer during a distance phase: the trial restarts once and ends as if unharmed."""
    sweep = napsp_sweep(
        tmp_path,
        "distance_kill",
        iterations=4,
        distance=SMALL["distance"] | {"hidden": [128, 128], "temporal_updates_per_episode": 300},
    )
    tracker = Tracker(default_tracking_uri(tmp_path))
    scheduler = SweepScheduler(load_sweep(sweep), tracker)
    killed = {}

    def kill_during_a_distance_phase():
        def trainer_mid_phase():
            active = scheduler._active
            if active and active[0].phase == "running" and active[0].round_index >= 1:
                if "distance" in (active[0].progress.get("text") or ""):
                    return active[0].group.workers["distance"][0]
            return None

        trainer = wait_for(trainer_mid_phase, timeout=300, interval=0.05, what="a distance phase after round 0")
        pid = ray.get(trainer.pid.remote())
        killed["round"] = scheduler._active[0].round_index
        os.kill(pid, signal.SIGKILL)
        killed["pid"] = pid

    killer = threading.Thread(target=kill_during_a_distance_phase, daemon=True)
    killer.start()
    outcome = scheduler.run()
    killer.join(timeout=5)
    assert killed and (outcome.finished, outcome.failed) == (1, 0)

    _, (child,) = sweep_runs(tracker.uri, "distance_kill")
    assert child.status == FINISHED and child.attempts == 1  # recovered in place: no new actor group
    assert child.metrics["recovered/lost_process"] == 1.0 and "failures/lost_process" not in child.metrics
    assert [s for s, _ in history(tracker, child.run_id, "icemlab.round")] == [0, 1, 2, 3]  # each round once
    assert [v for _, v in history(tracker, child.run_id, "distance_weights_version")] == [1, 2, 3, 4]
    # The restarted DistanceTrainer continued from the checkpoint: the same losses as an undisturbed run.
    expected = run_locally(METHODS["napsp"], load_sweep(sweep).trials[0].config.spec())
    for key in ("distance/temporal_loss", "distance/triangular_loss", "eval/final_goal_distance"):
        logged = [v for _, v in history(tracker, child.run_id, key)]
        assert logged == pytest.approx([v for r in expected for v in r.series[key]], rel=1e-6, nan_ok=True), key


@pytest.mark.slow
def test_driver_sigkill_then_resume_continues_from_the_last_iteration(tmp_path):
    sweep = napsp_sweep(tmp_path, "napsp_crash", seeds=(0, 1), iterations=4)
    uri = default_tracking_uri(tmp_path)
    driver = start_cli("run", str(sweep), "--max-concurrent", "1", "--quiet", cwd=tmp_path)
    tracker = Tracker(uri)
    try:

        def mid_trial():
            _, children = sweep_runs(uri, "napsp_crash")
            running = [c for c in children if c.status == RUNNING]
            return running and len(tracker.logged_rounds(running[0].run_id)) >= 2

        wait_for(mid_trial, timeout=300, what="a trial two iterations in")
        os.kill(driver.pid, signal.SIGKILL)  # the driver only; its Ray processes are orphaned
        driver.wait(timeout=30)
    finally:
        kill_group(driver)

    _, before = sweep_runs(uri, "napsp_crash")
    interrupted = {c.trial_key: c.run_id for c in before if c.status == RUNNING}
    assert len(interrupted) == 1

    result = cli("run", str(sweep), "--resume", "--quiet", cwd=tmp_path, timeout=600)
    assert result.returncode == 0, result.stderr
    parent, after = sweep_runs(uri, "napsp_crash")
    assert parent.status == FINISHED and all(c.status == FINISHED for c in after)
    assert sorted(c.trial_key for c in after) == sorted(t.key for t in load_sweep(sweep).trials)
    resumed = next(c for c in after if c.trial_key in interrupted)
    assert resumed.run_id == interrupted[resumed.trial_key] and resumed.attempts == 2
    for child in after:
        assert [s for s, _ in history(tracker, child.run_id, "icemlab.round")] == [0, 1, 2, 3]
        steps = [s for s, _ in history(tracker, child.run_id, "eval/success")]
        assert steps == [0, 1, 2, 3] and not [s for s, n in Counter(steps).items() if n > 1]
    trial = next(t for t in load_sweep(sweep).trials if t.key == resumed.trial_key)
    expected = run_locally(METHODS["napsp"], trial.config.spec())
    logged = [v for _, v in history(tracker, resumed.run_id, "distance/temporal_loss")]
    assert logged == pytest.approx([v for r in expected for v in r.series["distance/temporal_loss"]], rel=1e-6)
