"""What ran: the code's commit, the versions that decide the numbers.

Every trial's run records these (orchestrator/tracking.py names the tags),
with the CPU of the worker that ran it, so a result can be traced and re-run
next year. MuJoCo and gymnasium-robotics decide the physics: a resumed sweep
whose finished trials ran with other versions of them would mix two
simulators in one table, and is refused unless the user says otherwise.
"""

from __future__ import annotations

import platform
import subprocess
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path
from typing import NamedTuple

PACKAGES = ("mujoco", "gymnasium", "gymnasium-robotics", "torch", "ray", "mlflow", "numpy")
PHYSICS = ("mujoco", "gymnasium-robotics")
"""The packages whose versions change what the simulator computes."""
ROOT = Path(__file__).resolve().parents[1]


class Provenance(NamedTuple):
    """The code and the package versions of this process."""

    version: str
    """The icemlab package version."""
    commit: str | None
    """The git commit, when running from a checkout."""
    dirty: bool | None
    """Whether the checkout had uncommitted changes."""
    packages: dict[str, str]
    """Python's and the deciding packages' versions."""


def package_versions() -> dict[str, str]:
    """Versions of Python and of the packages that decide the results."""
    versions = {"python": platform.python_version()}
    for package in PACKAGES:
        try:
            versions[package] = version(package)
        except PackageNotFoundError:
            versions[package] = "not installed"
    return versions


def current() -> Provenance:
    """This process's code (commit and changes when it runs from a git checkout) and versions."""
    try:
        package = version("icemlab")
    except PackageNotFoundError:
        package = "dev"
    commit = dirty = None
    if (ROOT / ".git").exists():
        try:
            commit = _git("rev-parse", "HEAD")
            dirty = bool(_git("status", "--porcelain", "--untracked-files=no"))
        except (OSError, subprocess.CalledProcessError):
            pass
    return Provenance(package, commit, dirty, package_versions())


def _git(*args: str) -> str:
    command = ["git", "-C", str(ROOT), *args]
    return subprocess.run(command, capture_output=True, text=True, check=True, timeout=10).stdout.strip()


def physics_changes(recorded: dict[str, str]) -> dict[str, tuple[str, str]]:
    """package -> (recorded version, this version) for the physics packages that differ from a run's versions."""
    now = package_versions()
    return {p: (recorded[p], now[p]) for p in PHYSICS if p in recorded and recorded[p] != now[p]}
