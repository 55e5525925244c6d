"""Helpers shared by the service tests: sweep files, CLI subprocesses, MLflow lookups."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import yaml


def write_sweep(directory: Path, name: str = "tiny", **fields: Any) -> Path:
    """A small point_reach sweep; ``fields`` override or extend it."""
    sweep = {
        "name": name,
        "task": "point_reach",
        "algorithm": "icem",
        "base": {"planner": {"budget": 50, "horizon": 10}, "max_steps": 8},
        "seeds": [0],
    }
    sweep.update(fields)
    path = directory / f"{name}.yaml"
    path.write_text(yaml.safe_dump(sweep, sort_keys=False))
    return path


def cli(*args: str, cwd: Path, timeout: float = 300, env: dict | None = None) -> subprocess.CompletedProcess:
    """Run ``icemlab ARGS`` to completion in ``cwd``."""
    return subprocess.run(
        [sys.executable, "-m", "orchestrator.cli", *args],
        cwd=cwd,
        capture_output=True,
        text=True,
        timeout=timeout,
        env=_env(env),
    )


def start_cli(*args: str, cwd: Path, env: dict | None = None) -> subprocess.Popen:
    """Start ``icemlab ARGS`` in its own process group (as a terminal would run it)."""
    return subprocess.Popen(
        [sys.executable, "-m", "orchestrator.cli", *args],
        cwd=cwd,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        start_new_session=True,
        env=_env(env),
    )


def kill_group(process: subprocess.Popen) -> None:
    """Stop everything the CLI process started (its process group), then reap it."""
    try:
        os.killpg(process.pid, signal.SIGKILL)
    except ProcessLookupError:
        pass
    process.wait(timeout=30)


def _env(extra: dict | None) -> dict:
    env = dict(os.environ, RAY_USAGE_STATS_ENABLED="0", MLFLOW_DISABLE_TELEMETRY="true")
    env.pop("MLFLOW_TRACKING_URI", None)
    env.pop("RAY_ADDRESS", None)
    env.update(extra or {})
    return env


def wait_for(condition: Callable[[], Any], timeout: float, interval: float = 0.5, what: str = "condition"):
    """Poll until ``condition()`` is truthy; return its value."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            value = condition()
        except Exception:  # the store may be mid-write or not created yet
            value = None
        if value:
            return value
        time.sleep(interval)
    raise TimeoutError(f"timed out after {timeout}s waiting for {what}")


def sweep_runs(tracking_uri: str, name: str):
    """(parent run, child runs) of the latest run of sweep ``name``."""
    from orchestrator.tracking import Tracker

    tracker = Tracker(tracking_uri)
    parent = tracker.find_sweep_run(name, name)
    if parent is None:
        return None, []
    return parent, tracker.trial_runs(parent.run_id)
