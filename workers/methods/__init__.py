"""The thesis's methods as programs of rounds (see workers/methods/base.py), by the name sweeps give them."""

from __future__ import annotations

from workers.methods.base import (
    Artifact,
    LocalRoleGroup,
    MethodSettings,
    Program,
    Progress,
    RoleGroup,
    RoleSpec,
    RoundReport,
    TrialSpec,
    run_locally,
)
from workers.methods.mpc import MpcProgram, MpcSettings

METHODS: dict[str, type[Program]] = {program.name: program for program in (MpcProgram,)}
"""Registry: method name -> program class."""

DEFAULT_METHOD = "mpc"

__all__ = [
    "DEFAULT_METHOD",
    "METHODS",
    "Artifact",
    "LocalRoleGroup",
    "MethodSettings",
    "MpcProgram",
    "MpcSettings",
    "Program",
    "Progress",
    "RoleGroup",
    "RoleSpec",
    "RoundReport",
    "TrialSpec",
    "run_locally",
]
