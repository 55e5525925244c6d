"""What a local run opens to the network, and who may use it.

A local `icemlab run` starts a Ray reachable from this machine only: every
server of the run (GCS, raylet, workers, and the Prometheus exporters Ray
serves without a token) binds to the loopback. Ray's token authentication
stays on as well, so a process on this machine without the token cannot run
code through it. The test lists the listening sockets of a real run, checks
that none of them is bound beyond the loopback, that a Ray client without the
token is refused, and that the MLflow dashboard binds to 127.0.0.1 by default.
"""

from __future__ import annotations

import os
import socket
import subprocess
import sys
from pathlib import Path

from helpers import kill_group, start_cli, sweep_runs, wait_for, write_sweep

from orchestrator.cli import build_parser
from orchestrator.tracking import RUNNING, default_tracking_uri


def process_tree(root: int) -> set[int]:
    """``root`` and every process descending from it (from /proc)."""
    children: dict[int, list[int]] = {}
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                parent = int((entry / "stat").read_text().rsplit(")", 1)[1].split()[1])
            except (OSError, IndexError, ValueError):
                continue
            children.setdefault(parent, []).append(int(entry.name))
    tree, todo = set(), [root]
    while todo:
        pid = todo.pop()
        tree.add(pid)
        todo += children.get(pid, [])
    return tree


LOOPBACK = ("127.0.0.1", "::1", "::ffff:127.0.0.1")


def listening_sockets(pids: set[int]) -> list[tuple[int, str, int]]:
    """(pid, address, port) of every listening TCP socket the processes hold (from /proc)."""
    inodes: dict[str, int] = {}
    for pid in pids:
        try:
            for fd in Path(f"/proc/{pid}/fd").iterdir():
                target = os.readlink(fd)
                if target.startswith("socket:["):
                    inodes[target[8:-1]] = pid
        except OSError:
            continue
    found = []
    for table, width in (("/proc/net/tcp", 8), ("/proc/net/tcp6", 32)):
        for line in Path(table).read_text().splitlines()[1:]:
            fields = line.split()
            if fields[3] != "0A" or fields[9] not in inodes:  # 0A: LISTEN
                continue
            address, port = fields[1].split(":")
            raw = bytes.fromhex(address)
            if width == 8:
                host = socket.inet_ntop(socket.AF_INET, raw[::-1])
            else:
                words = b"".join(raw[i : i + 4][::-1] for i in range(0, 16, 4))
                host = socket.inet_ntop(socket.AF_INET6, words)
            found.append((inodes[fields[9]], host, int(port, 16)))
    return found


def test_a_local_run_exposes_nothing_without_the_token(tmp_path):
    sweep = write_sweep(
        tmp_path, "exposure", seeds=[0, 1, 2, 3], base={"planner": {"budget": 300, "horizon": 30}, "max_steps": 60}
    )
    uri = default_tracking_uri(tmp_path)
    # Even a user who switched Ray's authentication off gets it on for the local Ray icemlab starts.
    driver = start_cli("run", str(sweep), "--quiet", cwd=tmp_path, env={"RAY_AUTH_MODE": "disabled"})
    try:
        wait_for(
            lambda: driver.poll() is not None or any(c.status == RUNNING for c in sweep_runs(uri, "exposure")[1]),
            180,
            what="a trial",
        )
        assert driver.poll() is None, driver.stdout.read()
        sockets = listening_sockets(process_tree(driver.pid))
        commands = {pid: Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ")[:200] for pid, _, _ in sockets}
        gcs = [(host, port) for pid, host, port in sockets if b"gcs_server" in commands[pid]]
        assert gcs, f"no GCS among the run's sockets: {sockets}"
        exposed = [(host, port, commands[pid]) for pid, host, port in sockets if host not in LOOPBACK]
        assert not exposed, f"a local run listens beyond the loopback: {exposed}"

        host, port = gcs[0]
        address = f"127.0.0.1:{port}"
        probe = (
            "import ray\n"
            "try:\n"
            f"    ray.init(address={address!r}, logging_level='ERROR')\n"
            "    print('CONNECTED')\n"
            "except Exception as error:\n"
            "    print('REFUSED', type(error).__name__, error)\n"
        )
        home = tmp_path / "stranger"
        home.mkdir()
        environment = {k: v for k, v in os.environ.items() if not k.startswith("RAY_AUTH")}
        # A client that does not even try, and one without a token; both on this machine, in Ray's local-only
        # mode as the run (a client that looks for the node on another address never reaches it).
        for mode in ("disabled", "token"):
            try:
                result = subprocess.run(
                    [sys.executable, "-c", probe],
                    capture_output=True,
                    text=True,
                    timeout=120,
                    env=environment
                    | {"HOME": str(home), "RAY_AUTH_MODE": mode, "RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER": "0"},
                )
                stdout, stderr = result.stdout, result.stderr
            except subprocess.TimeoutExpired as timeout:
                # Ray's client may keep retrying a rejected handshake past the timeout; it is refused if the GCS
                # told it so, and it never connected.
                stdout, stderr = _text(timeout.stdout), _text(timeout.stderr)
                assert "Unauthenticated" in stderr, stdout + stderr
                stdout += "REFUSED (still retrying after the rejection)"
            assert "REFUSED" in stdout and "CONNECTED" not in stdout, stdout + stderr
    finally:
        kill_group(driver)


def _text(output: bytes | str | None) -> str:
    return output.decode(errors="replace") if isinstance(output, bytes) else (output or "")


def test_the_mlflow_dashboard_listens_on_localhost_by_default(monkeypatch):
    arguments = build_parser().parse_args(["ui"])
    assert arguments.host == "127.0.0.1"
    calls = []
    monkeypatch.setattr(subprocess, "call", lambda command, env: calls.append(command) or 0)
    from orchestrator.cli import cmd_ui

    assert cmd_ui(arguments) == 0
    assert calls[0][calls[0].index("--host") + 1] == "127.0.0.1"
