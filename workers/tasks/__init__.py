"""The thesis's tasks, by registry name: MuJoCo ground-truth tasks (chapter 3), learned-model tasks
(chapter 5) and goal tasks (chapter 6).

All kinds live in one registry, so sweeps name and validate them the same way
(``Task.Options``, ``make_task(name, options)``, ``task.options``); a method
says which kind it runs (``Program.task_problem``).
"""

from __future__ import annotations

import difflib
from typing import Any

from workers.tasks.adroit import Door, DoorSparse, Relocate
from workers.tasks.base import Frame, GroundTruthTask, RolloutBatch, SimState, StepOutcome, TaskOptions
from workers.tasks.bridge_maze import BridgeMaze
from workers.tasks.fetch import FetchPickPlaceSparse
from workers.tasks.goal_tasks import GOAL_TASKS, GoalTask
from workers.tasks.locomotion import HalfCheetahRunning, HumanoidStandup
from workers.tasks.model_based import ModelBasedTask
from workers.tasks.noisy import NoisyHalfCheetah
from workers.tasks.noisy_fetch import NoisyFetchPickPlace
from workers.tasks.point_reach import PointReach

TASKS: dict[str, type[GroundTruthTask] | type[ModelBasedTask] | type[GoalTask]] = {
    task.name: task
    for task in (
        HalfCheetahRunning,
        HumanoidStandup,
        FetchPickPlaceSparse,
        Door,
        DoorSparse,
        Relocate,
        PointReach,
        BridgeMaze,
        NoisyHalfCheetah,
        NoisyFetchPickPlace,
    )
} | dict(GOAL_TASKS)

GROUND_TRUTH_TASKS: tuple[str, ...] = tuple(name for name, task in TASKS.items() if issubclass(task, GroundTruthTask))
"""Names of the tasks with MuJoCo ground-truth planning models (chapter 3)."""


class UnknownTaskError(ValueError):
    """A task name that is not in the registry."""


def unknown_task_message(name: str) -> str:
    """'unknown task ...' with a did-you-mean hint and the list of tasks."""
    close = difflib.get_close_matches(name, TASKS, n=1)
    hint = f" (did you mean {close[0]!r}?)" if close else ""
    return f"unknown task {name!r}{hint}; known tasks: {', '.join(TASKS)}"


def unknown_option_message(task: str, option: str) -> str:
    """'<task> has no option ...' with a did-you-mean hint and the list of the task's options."""
    fields = list(TASKS[task].Options.model_fields)
    close = difflib.get_close_matches(option, fields, n=1)
    hint = f" (did you mean {close[0]!r}?)" if close else ""
    return f"{task} has no option {option!r}{hint}; its options: {', '.join(fields) or 'none'}"


def make_task(name: str, options: dict[str, Any] | None = None) -> GroundTruthTask | ModelBasedTask | GoalTask:
    """The task registered under ``name``, with its options (see each task's ``Options``)."""
    try:
        task_class = TASKS[name]
    except KeyError:
        raise UnknownTaskError(unknown_task_message(name)) from None
    return task_class(**(options or {}))


__all__ = [
    "GROUND_TRUTH_TASKS",
    "TASKS",
    "GoalTask",
    "ModelBasedTask",
    "Frame",
    "GroundTruthTask",
    "RolloutBatch",
    "SimState",
    "StepOutcome",
    "TaskOptions",
    "UnknownTaskError",
    "make_task",
    "unknown_option_message",
    "unknown_task_message",
]
