"""Ground-truth simulation as a role: simulation workers, and planning costs spread over them.

The planner asks for the costs of a batch; the pool splits it into contiguous
chunks, one per worker, and concatenates the answers in order. Results do not
depend on the split: every sequence is simulated from the same state, so a
trial gives the same numbers with one worker or several.

With ``ensemble`` settings (a noisy task, thesis App. D.4), every sequence is
simulated as P particles with their own draws of the task's noise, and the
costs are RAZER's (workers/dynamics/ground_truth.py). The pool draws the
noise for the whole batch and hands each worker its chunk's share, so the
split still does not change the results.

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
from workers.planning.icem import CostBatch
from workers.rollout import BatchEvaluator
from workers.tasks import TASKS, SimState, make_task

if TYPE_CHECKING:  # the methods package imports this module
    from workers.methods.base import RoleGroup


class SimulationWorker:
    """Evaluates batches of action sequences of one task in native MuJoCo.

    Args:
        task_name: registry name of the task.
        threads: native rollout threads of this worker.
        task_options: the task's options (its planning cost switches).
        ensemble: planning on noisy particles: ``particles`` and the fields of a RazerSettings (see
            :class:`~workers.methods.mpc.GroundTruthEnsembleSettings`); None: one noise-free rollout per sequence.
    """

    def __init__(
        self,
        task_name: str,
        threads: int = 1,
        task_options: dict[str, Any] | None = None,
        ensemble: dict[str, Any] | None = None,
    ):
        self.task = make_task(task_name, task_options)
        env = self.task.make_env()
        env.reset(seed=0)
        model = self.task.build_planning_model(env)
        env.close()
        self.evaluator = BatchEvaluator(self.task, model, threads)
        self.ensemble = None
        if ensemble is not None:
            from workers.dynamics.ground_truth import GroundTruthEnsembleEvaluator
            from workers.dynamics.settings import RazerSettings

            settings = dict(ensemble)
            particles = settings.pop("particles")
            razer = RazerSettings(mean_propagation="none", **settings)
            self.ensemble = GroundTruthEnsembleEvaluator(self.evaluator, razer, particles)
        self.incarnation = uuid.uuid4().hex
        """Changes when the worker is restarted, which lets callers count restarts."""

    def costs(self, state: SimState, actions: np.ndarray) -> tuple[np.ndarray, str]:
        """Planning costs (N,) of action sequences (N, h, d), and this worker's incarnation."""
        return self.evaluator.costs(state, actions), self.incarnation

    def ensemble_costs(
        self, state: SimState, actions: np.ndarray, draws: np.ndarray
    ) -> tuple[tuple[np.ndarray, dict[str, np.ndarray]], str]:
        """RAZER costs (total, components) of sequences (N, h, d) over their particles' draws (N, P, h, k)."""
        if self.ensemble is None:
            raise RuntimeError("this simulation worker was built without ensemble settings")
        return self.ensemble.costs(state, actions, draws), self.incarnation

    def current_incarnation(self) -> str:
        """This process's incarnation (see ``incarnation``)."""
        return self.incarnation

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
        ensemble: the workers' ensemble settings (see :class:`SimulationWorker`); None: plain ground truth.
        seed: seeds the particles' draws (ensemble only).
    """

    def __init__(
        self,
        task_name: str,
        threads: int | None,
        remote: RoleGroup | None = None,
        task_options: dict[str, Any] | None = None,
        ensemble: dict[str, Any] | None = None,
        seed: int = 0,
    ):
        if threads is None and (remote is None or remote.size == 0):
            raise ValueError("a simulation pool needs at least one worker")
        self.local = None if threads is None else SimulationWorker(task_name, threads, task_options, ensemble)
        self.draws = None
        if ensemble is not None:
            from workers.dynamics.ground_truth import StateDraws

            self.draws = StateDraws(seed, ensemble["particles"], TASKS[task_name].noise_dim)
        self.remote = remote if remote is not None and remote.size else None
        self._incarnations: list[str | None] = [None] * (self.remote.size if self.remote else 0)
        self.restarts = 0
        """Remote-worker restarts noticed so far (a restarted worker answers with a new incarnation)."""

    @property
    def size(self) -> int:
        return (self.local is not None) + (self.remote.size if self.remote else 0)

    def evaluate(self, state: PlanningState, actions: np.ndarray) -> np.ndarray | CostBatch:
        """Ground-truth planning costs of action sequences (N, h, d) from ``state.sim``: (N,) costs, or with
        ensemble settings a CostBatch of the RAZER totals and their components (c, c_A, u_A, ...)."""
        if state.sim is None:
            raise ValueError("ground-truth planning needs the simulator state")
        if self.draws is None:
            return np.concatenate(self._spread("costs", state.sim, np.array_split(actions, self.size)))
        draws = self.draws(state.sim, actions.shape[0], actions.shape[1])
        chunks = list(zip(np.array_split(actions, self.size), np.array_split(draws, self.size)))
        parts = self._spread("ensemble_costs", state.sim, chunks)
        total = np.concatenate([part[0] for part in parts])
        components = {name: np.concatenate([part[1][name] for part in parts]) for name in parts[0][1]}
        return CostBatch(total, "mean", components)

    def _spread(self, method: str, sim: SimState, chunks: list) -> list:
        """``method(sim, *chunk)`` per chunk: the first on the co-located worker, the others on remote ones."""
        chunks = [chunk if isinstance(chunk, tuple) else (chunk,) for chunk in chunks]
        local_chunk = chunks.pop(0) if self.local is not None else None
        # Remote calls first, so they run while the co-located worker simulates its chunk.
        calls = [(i, self.remote.submit(i, method, sim, *chunk)) for i, chunk in enumerate(chunks) if len(chunk[0])]
        parts = []
        if local_chunk is not None and len(local_chunk[0]):
            parts.append(getattr(self.local, method)(sim, *local_chunk)[0])
        for i, call in calls:
            result, incarnation = call.result()
            self._note_incarnation(i, incarnation)
            parts.append(result)
        return parts

    def _note_incarnation(self, member: int, incarnation: str) -> None:
        if self._incarnations[member] is not None and incarnation != self._incarnations[member]:
            self.restarts += 1
        self._incarnations[member] = incarnation

    def check_restarts(self) -> int:
        """Ask every remote worker for its incarnation; return ``restarts`` (the count so far).

        A worker that died after its last evaluation is restarted by the service without any call failing;
        without this check its loss would stay unnoticed until its next evaluation (never, at an episode's
        end), and the failure would not reach the episode's metrics.
        """
        if self.remote is not None:
            calls = [(i, self.remote.submit(i, "current_incarnation")) for i in range(self.remote.size)]
            for i, call in calls:
                self._note_incarnation(i, call.result())
        return self.restarts

    def close(self) -> None:
        if self.local is not None:
            self.local.close()
