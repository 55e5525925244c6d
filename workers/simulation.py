"""Ground-truth simulation as a role: simulation workers, and planning costs spread over them.

The planner asks for the costs of a batch; the pool splits it into contiguous
chunks, one per worker, and concatenates the answers in order. Results do not
depend on the split: every sequence is simulated from the same state, so a
trial gives the same numbers with one worker or several.

The pool's first worker lives in the process that plans (co-located): iCEM's
CEM-iterations are sequential, so every remote call costs a round trip per
iteration (about 1.5 ms measured on 2 cores, some 12% of a HalfCheetah step
at budget 100), while a co-located worker costs nothing. Further workers are
a :class:`~workers.methods.base.RoleGroup` of SimulationWorkers, possibly on
other machines.
"""

from __future__ import annotations

import os
import uuid
from typing import TYPE_CHECKING, Any

import numpy as np

from workers.mpc import PlanningState
from workers.rollout import BatchEvaluator
from workers.tasks import SimState, make_task

if TYPE_CHECKING:  # the methods package imports this module
    from workers.methods.base import RoleGroup


class SimulationWorker:
    """Evaluates batches of action sequences of one task in native MuJoCo.

    Args:
        task_name: registry name of the task.
        threads: native rollout threads of this worker.
        task_options: the task's options (its planning cost switches).
    """

    def __init__(self, task_name: str, threads: int = 1, task_options: dict[str, Any] | None = None):
        self.task = make_task(task_name, task_options)
        env = self.task.make_env()
        env.reset(seed=0)
        model = self.task.build_planning_model(env)
        env.close()
        self.evaluator = BatchEvaluator(self.task, model, threads)
        self.incarnation = uuid.uuid4().hex
        """Changes when the worker is restarted, which lets callers count restarts."""

    def costs(self, state: SimState, actions: np.ndarray) -> tuple[np.ndarray, str]:
        """Planning costs (N,) of action sequences (N, h, d), and this worker's incarnation."""
        return self.evaluator.costs(state, actions), self.incarnation

    def pid(self) -> int:
        """Process id (for fault-injection tests and diagnostics)."""
        return os.getpid()

    def close(self) -> None:
        self.evaluator.close()


class SimulationPool:
    """Evaluator over a co-located SimulationWorker plus a role group of remote ones.

    Args:
        task_name: task of the workers.
        threads: rollout threads of the co-located worker; None for none.
        remote: the ``simulation`` role's workers (may be empty or None).
        task_options: the task's options.
    """

    def __init__(
        self,
        task_name: str,
        threads: int | None,
        remote: RoleGroup | None = None,
        task_options: dict[str, Any] | None = None,
    ):
        if threads is None and (remote is None or remote.size == 0):
            raise ValueError("a simulation pool needs at least one worker")
        self.local = None if threads is None else SimulationWorker(task_name, threads, task_options)
        self.remote = remote if remote is not None and remote.size else None
        self._incarnations: list[str | None] = [None] * (self.remote.size if self.remote else 0)
        self.restarts = 0
        """Remote-worker restarts noticed so far (a restarted worker answers with a new incarnation)."""

    @property
    def size(self) -> int:
        return (self.local is not None) + (self.remote.size if self.remote else 0)

    def evaluate(self, state: PlanningState, actions: np.ndarray) -> np.ndarray:
        """(N,) ground-truth planning costs of action sequences (N, h, d) from ``state.sim``."""
        if state.sim is None:
            raise ValueError("ground-truth planning needs the simulator state")
        chunks = np.array_split(actions, self.size)
        local_chunk = chunks.pop(0) if self.local is not None else None
        # Remote calls first, so they run while the co-located worker simulates its chunk.
        calls = [(i, self.remote.submit(i, "costs", state.sim, chunk)) for i, chunk in enumerate(chunks) if len(chunk)]
        parts = []
        if local_chunk is not None and len(local_chunk):
            parts.append(self.local.costs(state.sim, local_chunk)[0])
        for i, call in calls:
            costs, incarnation = call.result()
            if self._incarnations[i] is not None and incarnation != self._incarnations[i]:
                self.restarts += 1
            self._incarnations[i] = incarnation
            parts.append(costs)
        return np.concatenate(parts)

    def close(self) -> None:
        if self.local is not None:
            self.local.close()
