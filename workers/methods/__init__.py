"""The thesis's methods as programs of rounds (see workers/methods/base.py), by the name sweeps give them."""

from __future__ import annotations

import importlib
import os

from workers.methods.apex import ApexProgram, ApexSettings
from workers.methods.base import (
    Artifact,
    LocalRoleGroup,
    MethodSettings,
    Program,
    Progress,
    RoleGroup,
    RoleSpec,
    RoleWorkerLost,
    RoundReport,
    TrialSpec,
    run_locally,
)
from workers.methods.mbrl import MbrlProgram, MbrlSettings
from workers.methods.mpc import MpcProgram, MpcSettings
from workers.methods.napsp import NapspProgram, NapspSettings

METHODS: dict[str, type[Program]] = {
    program.name: program for program in (MpcProgram, ApexProgram, MbrlProgram, NapspProgram)
}
"""Registry: method name -> program class."""

DEFAULT_METHOD = "mpc"
BUILTIN_METHODS = tuple(METHODS)
"""The methods icemlab ships (plugins come on top)."""

PLUGINS_VARIABLE = "ICEMLAB_PLUGINS"
"""Comma-separated modules imported with the registry: methods kept outside icemlab register themselves."""


def register(program: type[Program]) -> type[Program]:
    """Add a method to the registry (use as a class decorator in a plugin module)."""
    METHODS[program.name] = program
    return program


for _module in filter(None, (m.strip() for m in os.environ.get(PLUGINS_VARIABLE, "").split(","))):
    importlib.import_module(_module)

__all__ = [
    "ApexProgram",
    "ApexSettings",
    "BUILTIN_METHODS",
    "DEFAULT_METHOD",
    "METHODS",
    "Artifact",
    "MbrlProgram",
    "MbrlSettings",
    "LocalRoleGroup",
    "MethodSettings",
    "MpcProgram",
    "MpcSettings",
    "NapspProgram",
    "NapspSettings",
    "Program",
    "Progress",
    "RoleGroup",
    "RoleSpec",
    "RoleWorkerLost",
    "RoundReport",
    "TrialSpec",
    "register",
    "run_locally",
]
