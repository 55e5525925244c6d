"""``icemlab reproduce RUN_ID``: run one finished trial again from what its run recorded.

The run's ``trial.json`` holds the resolved configuration and seed; the trial
runs again in this process (its roles in-process) and its headline figures
are compared with the recorded ones. Ground-truth MPC is deterministic per
seed (native rollouts reproduce MuJoCo bit for bit, whatever the thread
count), so with the same versions the figures are identical; the versions
recorded with the run are compared too, since another MuJoCo may step
differently. Methods that train torch networks repeat only with the thread
count the trial ran with (torch sums in another order with other threads), so
that count is the default.
"""

from __future__ import annotations

import json
import math
import tempfile
from typing import NamedTuple

from orchestrator import provenance
from orchestrator.sweep import TrialConfig
from orchestrator.tracking import FINISHED, Tracker
from workers.methods import METHODS, run_locally
from workers.rollout import default_threads


class ReproduceError(ValueError):
    """A run that cannot be reproduced (unknown, not finished, no recorded configuration)."""


class Reproduction(NamedTuple):
    run_id: str
    figures: list[tuple[str, float, float]]
    """(summary metric, recorded, now)."""
    version_changes: dict[str, tuple[str, str]]
    """package -> (recorded, now) where they differ."""
    threads: int
    """CPUs per unit of work of this run."""
    recorded_threads: int | None
    """CPUs per unit of work the trial ran with (None: not recorded)."""

    @property
    def identical(self) -> bool:
        """Every headline figure as recorded; false when there was none to compare."""
        return bool(self.figures) and all(same_figure(recorded, now) for _, recorded, now in self.figures)


def same_figure(recorded: float, now: float) -> bool:
    """Equal, where a figure with nothing to measure (nan: a threshold never reached) equals itself."""
    return recorded == now or (math.isnan(recorded) and math.isnan(now))


def reproduce(tracker: Tracker, run_id: str, cpus: int | None = None) -> Reproduction:
    """Run the trial of ``run_id`` again with ``cpus`` per unit of work (default: as it ran, else all)."""
    run = tracker.trial_run(run_id)
    if run is None:
        raise ReproduceError(f"no trial run {run_id!r} in {tracker.uri}; `icemlab status SWEEP` lists run ids")
    if run.status != FINISHED:
        raise ReproduceError(f"run {run_id} is {run.status}: only a finished trial can be reproduced")
    with tempfile.TemporaryDirectory() as directory:
        try:
            recorded = json.loads(tracker.download(run_id, "trial.json", directory).read_text())
        except Exception as error:  # noqa: BLE001 - any store error means the same to the user
            raise ReproduceError(f"run {run_id} has no trial.json (recorded by icemlab 0.1 on): {error}") from None
    if not isinstance(recorded, dict) or "method" not in recorded:
        raise ReproduceError(f"run {run_id}'s trial.json is not a trial's configuration (it names no method)")
    if recorded["method"] not in METHODS:
        raise ReproduceError(f"run {run_id} ran method {recorded['method']!r}, which this icemlab does not have")
    try:
        config = TrialConfig.from_canonical(recorded)
    except (KeyError, TypeError, ValueError) as error:  # pydantic's ValidationError is a ValueError
        raise ReproduceError(f"run {run_id}'s trial.json does not load here: {error}") from None
    program = METHODS[config.method]
    if cpus is None:
        cpus = run.threads_per_worker or default_threads()
    reports = run_locally(program, config.spec(), unit_cpus=cpus)
    summary = reports[-1].summary
    figures = [
        (key, run.metrics[key], float(summary[key]))
        for key in program.metrics.values()
        if key in run.metrics and key in summary
    ]
    recorded_versions = run.versions
    changes = {
        name: (recorded_versions[name], now)
        for name, now in provenance.package_versions().items()
        if recorded_versions.get(name, now) != now
    }
    return Reproduction(run_id, figures, changes, cpus, run.threads_per_worker)
