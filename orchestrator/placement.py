"""A trial's actors on Ray: placed together, all or nothing, and torn down together.

A trial is a group: the ProgramRunner that hosts its program, and the workers
of every role the program declared (workers/methods/base.py RoleSpec). The
group is one Ray placement group with a bundle per actor, so it starts whole
or waits whole; a trial never runs with part of its roles missing, and CPUs
are counted across concurrent trials by Ray itself. An actor that reserves no
CPUs (a program whose runner only coordinates, a worker that computes only
while the others of its trial wait) gets no bundle of its own: Ray refuses
empty bundles, so it runs in the group's first bundle with num_cpus=0.

Role workers reach the program as :class:`RayRoleGroup` objects: the plain
RoleGroup interface of workers/, implemented with actor calls and the object
store. Stateless workers (pure functions of their arguments) are restarted by
Ray and their calls retried. A stateful worker is restarted too, but a call
it had in flight fails with RoleWorkerLost: its state went with the process,
so the runner restores the program from its last completed round and runs the
round again (workers/actors.py). Losing the runner itself ends the attempt;
the trial resumes from its last checkpoint in a new group.
"""

from __future__ import annotations

import functools
import inspect
from collections.abc import Mapping, Sequence
from typing import Any, NamedTuple

import ray
from ray.util.placement_group import placement_group, remove_placement_group
from ray.util.scheduling_strategies import PlacementGroupSchedulingStrategy

from workers import code_fingerprint
from workers.actors import ProgramRunner
from workers.methods import METHODS, RoleSpec, RoleWorkerLost, TrialSpec

LOST_ACTOR_ERRORS = (ray.exceptions.RayActorError, ray.exceptions.ActorUnavailableError)
"""What a call on an actor whose process died raises (it may be restarting, or gone)."""


def _get(role: str, ref: ray.ObjectRef) -> Any:
    try:
        return ray.get(ref)
    except LOST_ACTOR_ERRORS as error:  # the whole text: it says why (a memory kill, a node lost)
        raise RoleWorkerLost(role, f"{type(error).__name__}: {error}") from error
    except ray.exceptions.RayTaskError as error:  # a restarted stateful worker's refusal (restart_guarded)
        if isinstance(error.cause, RoleWorkerLost):
            raise RoleWorkerLost(error.cause.role, error.cause.cause) from None
        raise


def restart_guarded(role: RoleSpec) -> type:
    """The role's worker class, refusing calls on an instance Ray restarted until its state is loaded.

    A stateful worker killed between calls (an ensemble trainer while the round plans) is restarted by Ray
    without its state, and no call fails: the next call would work on from a fresh worker, silently. This
    subclass notices that it was restarted and raises RoleWorkerLost on every call but ``role.state_loader``
    (and ``pid``), so the runner restores the program from its last completed round, which hands the worker
    its state, and runs the round again, as for a loss during a call.
    """
    worker, loader = role.worker, role.state_loader

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        worker.__init__(self, *args, **kwargs)
        self._restarted_empty = ray.get_runtime_context().was_current_actor_reconstructed

    def guarded(name: str, method: Any) -> Any:
        @functools.wraps(method)
        def call(self, *args: Any, **kwargs: Any) -> Any:
            if self._restarted_empty and name not in (loader, "pid"):
                raise RoleWorkerLost(role.name, "the worker was lost between calls and restarted without its state")
            result = method(self, *args, **kwargs)
            if name == loader:
                self._restarted_empty = False
            return result

        return call

    methods = {
        name: guarded(name, member)
        for name, member in inspect.getmembers(worker, inspect.isfunction)
        if not name.startswith("_")
    }
    return type(worker.__name__, (worker,), {"__init__": __init__, **methods})


class RayPending:
    """A call under way on an actor."""

    def __init__(self, role: str, ref: ray.ObjectRef):
        self.role, self.ref = role, ref

    def result(self) -> Any:
        return _get(self.role, self.ref)

    def done(self) -> bool:
        # fetch_local=False: finished anywhere counts; the default would wait for a copy to this node.
        ready, _ = ray.wait([self.ref], timeout=0, fetch_local=False)
        return bool(ready)


class RayRoleGroup:
    """The actors of one role, behind the RoleGroup interface (picklable: it travels to the runner)."""

    def __init__(self, name: str, actors: Sequence[Any]):
        self.name = name
        self.actors = list(actors)
        self.size = len(self.actors)

    def submit(self, member: int, method: str, *args: Any) -> RayPending:
        return RayPending(self.name, getattr(self.actors[member], method).remote(*args))

    def map(self, method: str, arguments: Sequence[tuple]) -> list[Any]:
        """Each worker takes the next call as soon as it is free; results come back in order."""
        if not self.actors:
            raise RuntimeError(f"role {self.name!r} has no workers")
        results: list[Any] = [None] * len(arguments)
        queue = list(enumerate(arguments))
        in_flight: dict[ray.ObjectRef, tuple[int, int]] = {}

        def start(member: int) -> None:
            index, args = queue.pop(0)
            in_flight[getattr(self.actors[member], method).remote(*args)] = (index, member)

        for member in range(min(self.size, len(queue))):
            start(member)
        while in_flight:
            (ref,), _ = ray.wait(list(in_flight), num_returns=1)
            index, member = in_flight.pop(ref)
            results[index] = _get(self.name, ref)
            if queue:
                start(member)
        return results

    def share(self, value: Any) -> ray.ObjectRef:
        """One copy in the object store; passed as an argument, Ray hands every worker the value."""
        return ray.put(value)


class BundleLayout(NamedTuple):
    """The bundles of a trial's placement group and the bundle each actor runs in."""

    bundles: list[dict[str, float]]
    """Resources of each bundle (only actors that reserve something have one)."""
    runner: int
    """Bundle index of the runner."""
    roles: dict[str, list[int]]
    """Bundle index of each worker, by role."""


def bundle_layout(runner_cpus: float, roles: Sequence[RoleSpec]) -> BundleLayout:
    """One bundle per actor that reserves CPUs or GPUs; actors that reserve nothing run in the first bundle
    with CPUs (they compute on the CPUs of the actor whose bundle they share, never in a GPU-only bundle)."""
    bundles: list[dict[str, float]] = []
    SHARED = -1  # placeholder until the first bundle with CPUs is known

    def place(resources: dict[str, float]) -> int:
        if not any(resources.values()):
            return SHARED
        bundles.append(resources)
        return len(bundles) - 1

    runner = place({"CPU": float(runner_cpus)})
    indices = {
        role.name: [
            place({"CPU": float(role.cpus)} | ({"GPU": float(role.gpus)} if role.gpus else {}))
            for _ in range(role.count)
        ]
        for role in roles
    }
    with_cpus = [index for index, bundle in enumerate(bundles) if bundle["CPU"] > 0]
    if not with_cpus:
        raise ValueError("neither the runner nor any worker of the trial reserves CPUs: nothing to place")

    def resolve(index: int) -> int:
        return with_cpus[0] if index == SHARED else index

    return BundleLayout(bundles, resolve(runner), {name: [resolve(i) for i in ixs] for name, ixs in indices.items()})


def groups_that_fit(bundles: Sequence[Mapping[str, float]], node_cpus: Sequence[float], limit: int) -> int:
    """How many copies of a group with these bundles the nodes hold at once (at most ``limit``).

    A bundle lives on one node, so a trial's bundles must each fit a node's free CPUs; copies are packed
    greedily, largest bundle first into the node with the most CPUs left (Ray's PACK strategy spreads a
    group that does not fit one node the same way). Greedy packing can undercount what an optimal packing
    holds, never overcount.
    """
    free = sorted((float(c) for c in node_cpus), reverse=True)
    sizes = sorted((float(b.get("CPU", 0.0)) for b in bundles), reverse=True)
    for copies in range(limit):
        for size in sizes:
            node = max(range(len(free)), key=free.__getitem__, default=None)
            if node is None or free[node] + 1e-9 < size:
                return copies
            free[node] -= size
    return limit


class TrialGroup:
    """The placement group and actors of one trial attempt.

    Args:
        spec: the trial.
        unit_cpus: CPUs of one unit of work (see Program.roles_for).
        counts: worker counts per role from the sweep's resources.
        max_restarts: restarts allowed to each worker.
    """

    def __init__(
        self,
        spec: TrialSpec,
        unit_cpus: int,
        counts: Mapping[str, int],
        max_restarts: int,
    ):
        program = METHODS[spec.method]
        self.spec = spec
        self.roles: list[RoleSpec] = [r for r in program.roles_for(spec, unit_cpus, counts) if r.count]
        self.runner_cpus = program.runner_cpus(spec, unit_cpus)
        self.max_restarts = max_restarts
        self.layout = bundle_layout(self.runner_cpus, self.roles)
        self.bundles = self.layout.bundles
        # PACK keeps a trial on one node when it fits (no network between its actors), else spreads it.
        self.placement = placement_group(self.bundles, strategy="PACK")
        self.runner = None
        self.workers: dict[str, list[Any]] = {}

    @property
    def cpus(self) -> float:
        return sum(bundle["CPU"] for bundle in self.bundles)

    def ready(self) -> ray.ObjectRef:
        """Resolves when every bundle of the group is reserved."""
        return self.placement.ready()

    def start(self, recoveries: int = 0) -> Any:
        """Create the role workers and the runner in the reserved bundles; return the runner handle.

        ``recoveries``: stateful workers the runner may recover in place (the trial's lost-process budget left).
        """
        groups = {}
        for role in self.roles:
            # A stateful worker's call is not retried: the restarted process lacks the state it needs.
            actor_class = ray.remote(
                num_cpus=role.cpus,
                num_gpus=role.gpus,
                max_restarts=self.max_restarts,
                max_task_retries=0 if role.stateful else -1,
            )(restart_guarded(role) if role.stateful else role.worker)
            actors = []
            for bundle in self.layout.roles[role.name]:
                strategy = PlacementGroupSchedulingStrategy(self.placement, placement_group_bundle_index=bundle)
                actors.append(actor_class.options(scheduling_strategy=strategy).remote(**role.kwargs))
            self.workers[role.name] = actors
            groups[role.name] = RayRoleGroup(role.name, actors)
        runner_actor = ray.remote(num_cpus=self.runner_cpus, max_concurrency=2, max_restarts=0)(ProgramRunner)
        strategy = PlacementGroupSchedulingStrategy(self.placement, placement_group_bundle_index=self.layout.runner)
        self.runner = runner_actor.options(scheduling_strategy=strategy).remote(
            self.spec, groups, self.runner_cpus, code_fingerprint(), recoveries
        )
        return self.runner

    def stateless_restarts(self) -> dict[str, int]:
        """How often Ray has restarted the workers of each stateless role so far, by role.

        Their calls are retried on the restarted process and the round goes on, so no call fails and the
        runner never hears of the loss: the driver reads it here to record it.
        """
        return self._restarts(stateful=False)

    def stateful_restarts(self) -> dict[str, int]:
        """How often Ray has restarted the workers of each stateful role so far, by role.

        The runner reports each one it recovers; the driver compares after every round, as a trial finishes and when
        an attempt ends, to record those no report accounts for (one whose next call was its state loader, one
        whose report died with the runner).
        """
        return self._restarts(stateful=True)

    def _restarts(self, stateful: bool) -> dict[str, int]:
        """Restarts by role, read from the cluster's actor table (the GCS, which needs no dashboard). An actor
        whose entry cannot be read counts 0."""
        from ray._private import state

        counts: dict[str, int] = {}
        for role in self.roles:
            if role.stateful != stateful:
                continue
            counts[role.name] = 0
            for actor in self.workers.get(role.name, []):
                try:
                    counts[role.name] += int(state.actors(actor_id=actor._actor_id.hex()).get("NumRestarts", 0))
                except Exception:  # noqa: BLE001 - a table read racing the cluster's end: nothing to add
                    pass
        return counts

    def actors(self) -> list[Any]:
        """Every actor of the group (runner first)."""
        return ([self.runner] if self.runner is not None else []) + [
            a for group in self.workers.values() for a in group
        ]

    def teardown(self) -> None:
        for actor in self.actors():
            try:
                ray.kill(actor)
            except Exception:  # already gone
                pass
        try:
            remove_placement_group(self.placement)
        except Exception:  # Ray going down
            pass
