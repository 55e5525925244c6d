"""Provenance on every run, re-running a trial by its id, and resumes that would mix two simulators."""

from __future__ import annotations

import json

import pytest
from helpers import cli, sweep_runs, write_sweep

from orchestrator import provenance
from orchestrator.reproduce import reproduce
from orchestrator.sweep import load_sweep
from orchestrator.tracking import FINISHED, PARAM_THREADS, Tracker, default_tracking_uri
from workers.methods import METHODS, run_locally


@pytest.mark.slow  # several sweeps through the CLI
def test_runs_record_what_ran_and_reproduce_gives_the_identical_return(tmp_path):
    sweep = write_sweep(
        tmp_path, "provenance", seeds=[0, 1], base={"planner": {"budget": 50, "horizon": 10}, "max_steps": 12}
    )
    assert cli("run", str(sweep), "--quiet", cwd=tmp_path).returncode == 0
    tracker = Tracker(default_tracking_uri(tmp_path))
    _, children = sweep_runs(tracker.uri, "provenance")
    versions = provenance.package_versions()
    for child in children:
        assert child.status == FINISHED
        assert len(child.tags["icemlab.commit"]) == 40 and child.tags["icemlab.dirty"] in ("true", "false")
        for package in ("python", "mujoco", "gymnasium-robotics", "torch", "ray", "mlflow", "numpy"):
            assert child.tags[f"version.{package}"] == versions[package]
        assert child.machine["cpu_model"] and int(child.machine["cpus"]) >= 1
        recorded = json.loads(tracker.download(child.run_id, "trial.json", tmp_path / child.run_id).read_text())
        trial = next(t for t in load_sweep(sweep).trials if t.key == child.trial_key)
        assert recorded == trial.config.canonical()  # the fully resolved settings

    status = cli("status", str(sweep), "--provenance", cwd=tmp_path)
    assert children[0].tags["icemlab.commit"] in status.stdout and f"mujoco {versions['mujoco']}" in status.stdout

    again = cli("reproduce", children[0].run_id, cwd=tmp_path)
    assert again.returncode == 0, again.stdout + again.stderr
    assert "mean_return: recorded" in again.stdout and again.stdout.strip().endswith("identical")

    # A resume whose finished trials ran another MuJoCo is refused, and changes nothing.
    tracker.set_tags(children[0].run_id, {"version.mujoco": "3.10.0"})
    resumed = cli("run", str(sweep), "--resume", "--quiet", cwd=tmp_path)
    assert resumed.returncode == 2
    assert f"{sweep}: finished trials of sweep provenance ran another simulator" in resumed.stderr
    assert (
        f"mujoco 3.10.0 then, {versions['mujoco']} now" in resumed.stderr and "--allow-physics-change" in resumed.stderr
    )
    parent, after = sweep_runs(tracker.uri, "provenance")
    assert parent.status == FINISHED and [c.status for c in after] == [FINISHED, FINISHED]
    allowed = cli("run", str(sweep), "--resume", "--allow-physics-change", "--quiet", cwd=tmp_path)
    assert allowed.returncode == 0 and "already done" in allowed.stderr


def test_reproduce_refuses_unknown_and_unfinished_runs(tmp_path):
    tracker = Tracker(default_tracking_uri(tmp_path))
    unknown = cli("reproduce", "0123456789abcdef0123456789abcdef", cwd=tmp_path)
    assert unknown.returncode == 2 and "no trial run" in unknown.stderr
    parent = tracker.start_sweep("x", "x", "hash", "name: x\n", {}, "dev")
    running = tracker.start_trial(parent, "key", "trial", {}, {})
    unfinished = cli("reproduce", running, cwd=tmp_path)
    assert unfinished.returncode == 2 and "is RUNNING: only a finished trial can be reproduced" in unfinished.stderr
    assert tracker.trial_run(running).status == "RUNNING"  # nothing changed


def test_reproduce_refuses_a_trial_json_that_is_no_trials_configuration(tmp_path):
    tracker = Tracker(default_tracking_uri(tmp_path))
    parent = tracker.start_sweep("x", "x", "hash", "name: x\n", {}, "dev")
    run_id = tracker.start_trial(parent, "key", "trial", {}, {}, {"trial.json": json.dumps({"seed": 0})})
    tracker.end_trial(run_id, FINISHED, {})
    refused = cli("reproduce", run_id, cwd=tmp_path)
    assert refused.returncode == 2 and "trial.json is not a trial's configuration" in refused.stderr, refused.stderr


def test_reproduce_runs_with_the_thread_count_the_trial_ran_with(tmp_path):
    """Torch-trained figures depend on the thread count, so a reproduction uses the recorded one."""
    sweep = write_sweep(tmp_path, "toy_threads", method="toy", base={"rounds": 2, "steps": 5}, algorithm=None)
    (trial,) = load_sweep(sweep).trials
    (recorded,) = [r.summary for r in run_locally(METHODS["toy"], trial.config.spec()) if r.summary]
    tracker = Tracker(default_tracking_uri(tmp_path))
    parent = tracker.start_sweep("toy_threads", "toy_threads", "hash", sweep.read_text(), {}, "dev")
    artifacts = {"trial.json": json.dumps(trial.config.canonical())}
    run_id = tracker.start_trial(parent, trial.key, "toy", {PARAM_THREADS: 3}, {}, artifacts)
    tracker.end_trial(run_id, FINISHED, recorded)

    again = reproduce(tracker, run_id)
    assert (again.threads, again.recorded_threads) == (3, 3) and again.identical
    assert reproduce(tracker, run_id, cpus=1).threads == 1
    told = cli("reproduce", run_id, "--threads", "1", cwd=tmp_path)
    assert "note: the run used 3 thread(s) per worker, this 1" in told.stdout, told.stdout + told.stderr


@pytest.mark.slow  # several sweeps through the CLI
def test_validate_plans_from_the_store_or_a_calibration(tmp_path):
    """A plan lists finished trials and estimates core-hours and wall time; it never creates a store."""
    sweep = write_sweep(
        tmp_path, "planned", seeds=[0, 1], base={"planner": {"budget": 50, "horizon": 10}, "max_steps": 12}
    )
    fresh = cli("validate", str(sweep), "--cores", "64", cwd=tmp_path)
    assert fresh.returncode == 0 and not (tmp_path / "mlflow.db").exists()
    assert "plan: 2 trial(s) to run, 0 already finished" in fresh.stdout
    assert "from a calibration here" in fresh.stdout and "a cluster of 64 CPUs: about" in fresh.stdout
    assert cli("run", str(sweep), "--quiet", cwd=tmp_path).returncode == 0
    sweep.write_text(sweep.read_text().replace("- 1\n", "- 1\n- 2\n"))  # one more seed
    planned = cli("run", str(sweep), "--dry-run", cwd=tmp_path)
    assert planned.returncode == 0 and planned.stdout.count("(finished)") == 2
    assert "plan: 1 trial(s) to run, 2 already finished" in planned.stdout
    assert "from 2 past run(s)" in planned.stdout  # the finished trials' measured cost


def test_a_figure_with_nothing_to_measure_reproduces_as_itself_and_no_figures_prove_nothing():
    """napsp logs nan for a threshold never reached: nan again is identical. A reproduction that shares no
    headline figure with its run is not called identical."""
    from orchestrator.reproduce import Reproduction

    def outcome(figures):
        return Reproduction("id", figures, {}, 1, 1)

    assert outcome([("episodes_to_success", float("nan"), float("nan")), ("eval_success", 0.5, 0.5)]).identical
    assert not outcome([("episodes_to_success", float("nan"), 120.0)]).identical
    assert not outcome([]).identical


def test_reproduce_says_when_there_is_nothing_to_compare_or_no_store(tmp_path):
    sweep = write_sweep(tmp_path, "toy_bare", method="toy", base={"rounds": 1, "steps": 2}, algorithm=None)
    (trial,) = load_sweep(sweep).trials
    missing = cli("reproduce", "0123456789abcdef0123456789abcdef", cwd=tmp_path)
    assert missing.returncode == 2 and "no store at" in missing.stderr
    assert not (tmp_path / "mlflow.db").exists()  # asking created none
    tracker = Tracker(default_tracking_uri(tmp_path))
    parent = tracker.start_sweep("toy_bare", "toy_bare", "hash", sweep.read_text(), {}, "dev")
    artifacts = {"trial.json": json.dumps(trial.config.canonical())}
    run_id = tracker.start_trial(parent, trial.key, "toy", {PARAM_THREADS: 1}, {}, artifacts)
    tracker.end_trial(run_id, FINISHED, {})  # finished without its summary figures
    bare = cli("reproduce", run_id, cwd=tmp_path)
    assert bare.returncode == 1 and "nothing to compare" in bare.stdout and "identical" not in bare.stdout
