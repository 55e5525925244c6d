"""What ran: the code's commit, the versions that decide the numbers, the machine.

Every trial's run records these as tags (``icemlab.commit``, ``icemlab.dirty``,
``version.<package>``, and from the worker that ran it ``icemlab.cpu_model``,
``icemlab.cpus``, ``icemlab.host``), so a result can be traced and re-run
next year. MuJoCo and gymnasium-robotics decide the physics: a resumed sweep
whose finished trials ran with other versions of them would mix two
simulators in one table, and is refused unless the user says otherwise.
"""

from __future__ import annotations

import platform
import subprocess
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path

PACKAGES = ("mujoco", "gymnasium", "gymnasium-robotics", "torch", "ray", "mlflow", "numpy")
PHYSICS = ("mujoco", "gymnasium-robotics")
"""The packages whose versions change what the simulator computes."""
VERSION_TAG = "version."
ROOT = Path(__file__).resolve().parents[1]


def package_versions() -> dict[str, str]:
    """Versions of Python and of the packages that decide the results."""
    versions = {"python": platform.python_version()}
    for package in PACKAGES:
        try:
            versions[package] = version(package)
        except PackageNotFoundError:
            versions[package] = "not installed"
    return versions


def code_version() -> dict[str, str]:
    """The icemlab package version and, when it runs from a git checkout, the commit and whether it had changes."""
    try:
        package = version("icemlab")
    except PackageNotFoundError:
        package = "dev"
    found = {"icemlab.version": package}
    if (ROOT / ".git").exists():
        try:
            commit = _git("rev-parse", "HEAD")
            dirty = bool(_git("status", "--porcelain", "--untracked-files=no"))
            found |= {"icemlab.commit": commit, "icemlab.dirty": str(dirty).lower()}
        except (OSError, subprocess.CalledProcessError):
            pass
    return found


def _git(*args: str) -> str:
    return subprocess.run(
        ["git", "-C", str(ROOT), *args], capture_output=True, text=True, check=True, timeout=10
    ).stdout.strip()


def run_tags() -> dict[str, str]:
    """The driver-side provenance tags of a trial's run."""
    return code_version() | {VERSION_TAG + name: value for name, value in package_versions().items()}


def physics_changes(recorded: dict[str, str]) -> dict[str, tuple[str, str]]:
    """package -> (recorded version, this version) for the physics packages that differ from a run's tags."""
    current = package_versions()
    changes = {}
    for package in PHYSICS:
        before = recorded.get(VERSION_TAG + package)
        if before is not None and before != current[package]:
            changes[package] = (before, current[package])
    return changes
