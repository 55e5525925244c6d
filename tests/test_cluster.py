"""A sweep on a real two-node Ray cluster, logging to a real MLflow server (marker: cluster).

Both nodes and the server run on this machine: `ray start --head` plus
`ray start --address`, each node offering one CPU, and `mlflow server` on
127.0.0.1. Every trial asks for two CPUs at once (its runner and one remote
SimulationWorker), so no trial can finish without using both nodes.
Takes about a minute.
"""

from __future__ import annotations

import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
import urllib.request
from pathlib import Path

import pytest
from helpers import cli, wait_for, write_sweep

pytestmark = pytest.mark.cluster

VENV_BIN = Path(sys.executable).parent
# Ray enables token authentication on `ray start` clusters; a driver given an
# explicit address only authenticates when asked to (the token is ~/.ray/auth_token).
AUTH = {"RAY_AUTH_MODE": "token"}


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def start(command: list[str], log: Path, env: dict | None = None) -> subprocess.Popen:
    """A long-running process in its own process group, output to ``log``."""
    return subprocess.Popen(
        command,
        stdout=log.open("w"),
        stderr=subprocess.STDOUT,
        start_new_session=True,
        env=dict(os.environ, RAY_USAGE_STATS_ENABLED="0", **(env or {})),
    )


def stop(process: subprocess.Popen) -> None:
    """SIGTERM the process group, SIGKILL what is left after 10 s (gcs_server needs it)."""
    for sig, grace in ((signal.SIGTERM, 10), (signal.SIGKILL, 10)):
        try:
            os.killpg(process.pid, sig)
        except ProcessLookupError:
            break
        try:
            process.wait(timeout=grace)
            break
        except subprocess.TimeoutExpired:
            continue


def alive_nodes(address: str) -> tuple[int, int]:
    """(alive nodes, CPUs) of the cluster at ``address``, asked from a fresh driver."""
    probe = (
        f"import ray; ray.init(address={address!r}, logging_level='ERROR'); "
        "print(sum(n['Alive'] for n in ray.nodes()), int(ray.cluster_resources().get('CPU', 0)))"
    )
    out = subprocess.run(
        [sys.executable, "-c", probe], capture_output=True, text=True, timeout=60, env=dict(os.environ, **AUTH)
    ).stdout.split()
    return (int(out[-2]), int(out[-1])) if len(out) >= 2 else (0, 0)


@pytest.fixture
def cluster(tmp_path):
    temp_dir = tempfile.mkdtemp(prefix="icr", dir="/tmp")  # short: socket paths are length-limited
    port = free_port()
    address = f"127.0.0.1:{port}"
    common = ["--num-cpus=1", "--disable-usage-stats", "--block"]
    head = start(
        [
            str(VENV_BIN / "ray"),
            "start",
            "--head",
            "--node-ip-address=127.0.0.1",
            f"--port={port}",
            f"--temp-dir={temp_dir}",
            "--include-dashboard=false",
            *common,
        ],
        tmp_path / "head.log",
    )
    nodes = [head]
    try:
        wait_for(lambda: alive_nodes(address)[0] >= 1, timeout=120, interval=2, what="the head node")
        nodes.append(
            start(
                [str(VENV_BIN / "ray"), "start", f"--address={address}", "--node-ip-address=127.0.0.1", *common],
                tmp_path / "worker.log",
                env=AUTH,
            )
        )
        wait_for(lambda: alive_nodes(address) == (2, 2), timeout=120, interval=2, what="two nodes with 2 CPUs")
        yield address
    finally:
        for node in reversed(nodes):
            stop(node)
        shutil.rmtree(temp_dir, ignore_errors=True)


@pytest.fixture
def mlflow_server(tmp_path):
    port = free_port()
    server = start(
        [
            sys.executable,
            "-m",
            "mlflow",
            "server",
            "--backend-store-uri",
            f"sqlite:///{tmp_path / 'server.db'}",
            "--artifacts-destination",
            str(tmp_path / "server-artifacts"),
            "--serve-artifacts",
            "--host",
            "127.0.0.1",
            "--port",
            str(port),
            "--workers",
            "1",
        ],
        tmp_path / "mlflow.log",
        env={"MLFLOW_SERVER_ENABLE_JOB_EXECUTION": "false", "MLFLOW_DISABLE_TELEMETRY": "true"},
    )
    url = f"http://127.0.0.1:{port}"
    try:
        wait_for(
            lambda: urllib.request.urlopen(f"{url}/health", timeout=2).status == 200, timeout=120, what="mlflow server"
        )
        yield url
    finally:
        stop(server)


def test_sweep_on_two_node_cluster_with_mlflow_server(tmp_path, cluster, mlflow_server):
    sweep = write_sweep(
        tmp_path,
        "two_nodes",
        seeds=[0, 1],
        resources={"simulation_workers": 2, "threads_per_worker": 1},
    )
    started = time.monotonic()
    result = cli(
        "run", str(sweep), "--address", cluster, "--tracking-uri", mlflow_server, "--quiet", cwd=tmp_path, env=AUTH
    )
    assert result.returncode == 0, result.stderr[-3000:]
    assert not (tmp_path / "mlflow.db").exists()  # everything went to the server

    from mlflow.tracking import MlflowClient

    client = MlflowClient(mlflow_server)
    experiment = client.get_experiment_by_name("two_nodes")
    runs = client.search_runs([experiment.experiment_id])
    parents = [r for r in runs if r.data.tags.get("icemlab.kind") == "sweep"]
    children = [r for r in runs if r.data.tags.get("icemlab.kind") == "trial"]
    assert len(parents) == 1 and parents[0].info.status == "FINISHED"
    assert len(children) == 2 and {c.info.status for c in children} == {"FINISHED"}
    assert {c.data.tags["seed"] for c in children} == {"0", "1"}
    for child in children:
        assert child.data.tags["mlflow.parentRunId"] == parents[0].info.run_id
        assert child.data.params["resources.simulation_workers"] == "2"
        assert "episode_return" in child.data.metrics
        assert len(client.get_metric_history(child.info.run_id, "step/reward")) == 8
        # Checkpoints go through the server's proxied artifact store like every other file.
        assert [a.path for a in client.list_artifacts(child.info.run_id, "checkpoints")] == ["checkpoints/round_000000"]
    artifacts = {a.path for a in client.list_artifacts(parents[0].info.run_id)}
    assert {"sweep.yaml", "summary.csv", "curves.png"} <= artifacts  # proxied through the server
    print(f"two-node sweep took {time.monotonic() - started:.1f} s")


def test_one_cpu_nodes_get_one_cpu_bundles_and_a_bundle_larger_than_every_node_is_refused(tmp_path, cluster):
    """The cluster has 2 CPUs but no node with 2: by default a lone trial plans with 1-CPU units instead of
    waiting forever for a 2-CPU bundle; a sweep that pins 2 threads per worker is refused before it starts."""
    result = cli("run", str(write_sweep(tmp_path, "units")), "--address", cluster, "--quiet", cwd=tmp_path, env=AUTH,
                 timeout=240)
    assert result.returncode == 0, result.stderr[-3000:]
    pinned = write_sweep(tmp_path, "pinned", resources={"threads_per_worker": 2})
    result = cli("run", str(pinned), "--address", cluster, "--quiet", cwd=tmp_path, env=AUTH, timeout=120)
    assert result.returncode != 0
    assert "bundles of 2 CPUs, each on one node" in result.stderr and "nodes have 1, 1 CPUs" in result.stderr


# A driver on the cluster: an actor on the node the driver is not on returns a result too large to travel
# inline (it stays in that node's object store), and done() is asked once the result is known to be finished.
REMOTE_RESULT_PROBE = """
import ray, numpy as np
from ray.util.scheduling_strategies import NodeAffinitySchedulingStrategy
from orchestrator.placement import RayPending

ray.init(address={address!r}, logging_level="ERROR")
here = ray.get_runtime_context().get_node_id()
there = next(n["NodeID"] for n in ray.nodes() if n["Alive"] and n["NodeID"] != here)

@ray.remote(num_cpus=1)
class Episode:
    def run(self):
        return np.ones(4_000_000)

actor = Episode.options(scheduling_strategy=NodeAffinitySchedulingStrategy(there, soft=False)).remote()
ref = actor.run.remote()
ready, _ = ray.wait([ref], timeout=120, fetch_local=False)
assert ready, "the remote call did not finish"
print("done:", RayPending("episode", ref).done())
"""


def test_a_call_finished_on_another_node_is_done_before_its_result_is_fetched(cluster):
    """Frozen-row progress counts the planner actors' finished episodes with done(); one finished on another
    node must count at once, not after its result has been copied to the driver's node."""
    probe = subprocess.run(
        [sys.executable, "-c", REMOTE_RESULT_PROBE.format(address=cluster)],
        capture_output=True, text=True, timeout=240, env=dict(os.environ, RAY_USAGE_STATS_ENABLED="0", **AUTH),
    )  # fmt: skip
    assert probe.returncode == 0, probe.stderr[-3000:]
    assert "done: True" in probe.stdout
