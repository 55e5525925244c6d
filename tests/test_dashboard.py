"""The MLflow dashboard, seen in a real browser (marker: browser).

Runs a small sweep, serves the embedded store with `icemlab ui`, follows the
link it prints to the sweep's runs, opens the sweep's parent run and one child
run in headless Chromium and checks that the runs and their metrics are on the
rendered pages. The screenshot of the parent
run is kept in test-artifacts/dashboard.png. Needs Debian's chromium package.
"""

from __future__ import annotations

import html
import re
import shutil
import subprocess
import tempfile
import urllib.request
from pathlib import Path

import pytest
from helpers import cli, kill_group, start_cli, sweep_runs, wait_for, write_sweep

from orchestrator.tracking import default_tracking_uri

pytestmark = pytest.mark.browser

ARTIFACTS = Path(__file__).resolve().parents[1] / "test-artifacts"
CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
# Without a virtual-time budget headless Chromium captures MLflow's loading skeleton.
FLAGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--no-first-run",
    "--disable-quic",
    "--window-size=1400,1000",
    "--virtual-time-budget=20000",
]


def browse(url: str, *extra: str) -> str:
    """Render ``url`` in headless Chromium; return the visible text of the page (or take a screenshot)."""
    action = extra or ("--dump-dom",)
    with tempfile.TemporaryDirectory() as profile:
        result = subprocess.run(
            [CHROMIUM, *FLAGS, f"--user-data-dir={profile}", *action, url], capture_output=True, text=True, timeout=120
        )
    page = re.sub(r"<style.*?</style>|<script.*?</script>", " ", result.stdout, flags=re.S)
    return html.unescape(re.sub(r"\s+", " ", re.sub(r"<[^>]+>", " ", page)))


@pytest.mark.skipif(CHROMIUM is None, reason="needs Chromium: apt-get install chromium")
def test_dashboard_shows_the_sweep_runs_and_metrics(tmp_path):
    sweep = write_sweep(tmp_path, "dashboard", parameters={"algorithm": {"values": ["icem", "cem_mpc"]}})
    assert cli("run", str(sweep), "--quiet", cwd=tmp_path).returncode == 0
    parent, children = sweep_runs(default_tracking_uri(tmp_path), "dashboard")

    port = 5000 + (abs(hash(str(tmp_path))) % 900) + 50
    server = start_cli("ui", "--port", str(port), cwd=tmp_path)
    base = f"http://127.0.0.1:{port}"
    try:
        link = None
        for line in server.stdout:  # icemlab ui prints a link per sweep before MLflow starts
            if line.strip().startswith("dashboard: http"):
                link = line.split(": ", 1)[1].strip()
                break
        wait_for(
            lambda: urllib.request.urlopen(f"{base}/health", timeout=2).status == 200, timeout=90, what="the MLflow UI"
        )
        # The printed link opens the sweep's runs; the experiment's own page opens MLflow's GenAI overview,
        # whatever the experiment's kind tag says (MLflow 3.17), which is why the links carry workflowType.
        runs_page = browse(link)
        assert "Model training" in runs_page and "matching runs" in runs_page and "dashboard" in runs_page
        assert "Detect Issues" in browse(f"{base}/#/experiments/{parent.experiment_id}")
        experiment = parent.experiment_id
        parent_url = f"{base}/#/experiments/{experiment}/runs/{parent.run_id}"
        page = browse(parent_url)
        assert "dashboard" in page and "Finished" in page
        for child in children:  # the child runs are listed by name on the parent's page
            assert child.tags["mlflow.runName"] in page
        assert "trials_finished" in page  # the parent's metrics

        child = children[0]
        child_page = browse(f"{base}/#/experiments/{experiment}/runs/{child.run_id}")
        for metric in ("episode_return", "simulated_steps_per_second", "planning_seconds_per_step"):
            assert metric in child_page
        assert f"{child.metrics['episode_return']}"[:6] in child_page  # the value itself, not just the name

        ARTIFACTS.mkdir(exist_ok=True)
        screenshot = ARTIFACTS / "dashboard.png"
        browse(parent_url, f"--screenshot={screenshot}")
        assert screenshot.exists() and screenshot.stat().st_size > 20_000  # a rendered page, not a skeleton
    finally:
        kill_group(server)
