"""Shared fixtures: tasks, their real environments and planning models are costly to build, so build them once."""

from __future__ import annotations

import os

import pytest

os.environ.setdefault("MLFLOW_DISABLE_TELEMETRY", "true")
os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
# The toy learning method of the service tests is a plugin, as a method kept outside icemlab would be;
# Ray's worker processes inherit the variables and find it on the path.
TESTS = os.path.dirname(os.path.abspath(__file__))
# The checkout under test comes first: an editable install of another checkout (a git worktree's shared
# venv) would otherwise serve the CLI subprocesses and Ray workers its own code.
ROOT = os.path.dirname(TESTS)
os.environ["ICEMLAB_PLUGINS"] = "toy_method"
os.environ["PYTHONPATH"] = os.pathsep.join(filter(None, [ROOT, TESTS, os.environ.get("PYTHONPATH")]))


@pytest.fixture(autouse=True)
def restore_environment():
    """The command line sets Ray's variables for the process it runs in (cli.secure_local_ray); a test that
    calls it in-process must not hand them to the Ray a later test starts in this process."""
    saved = dict(os.environ)
    yield
    os.environ.clear()
    os.environ.update(saved)


@pytest.fixture(scope="session")
def task_bundle():
    """task name -> (task, env, planning model), built on first use."""
    from workers.tasks import make_task

    cache = {}

    def get(name: str):
        if name not in cache:
            task = make_task(name)
            env = task.make_env()
            env.reset(seed=0)
            cache[name] = (task, env, task.build_planning_model(env))
        return cache[name]

    yield get
    for _, env, _ in cache.values():
        env.close()
