"""A stateful worker lost mid-round costs that round only, inside the runner (no Ray: in-process roles).

The role group below stands for Ray's restarted actor: on the call it is told
to lose, it replaces its worker with a fresh one (the state is gone, as with a
new process) and raises RoleWorkerLost, as orchestrator/placement.py does for
a dead actor.
"""

from __future__ import annotations

import pickle

import pytest
import toy_method

from workers.actors import ProgramRunner
from workers.methods import LocalRoleGroup, RoleWorkerLost, TrialSpec
from workers.methods.base import RoleSpec


class LosingGroup(LocalRoleGroup):
    """Loses its worker on the listed calls of ``method`` (counted from 1), then serves a fresh one."""

    def __init__(self, spec: RoleSpec, method: str, lose_on: set[int]):
        super().__init__(spec.name, [spec.worker(**spec.kwargs)])
        self.spec, self.method, self.lose_on, self.calls = spec, method, set(lose_on), 0

    def submit(self, member: int, method: str, *args):
        if method == self.method:
            self.calls += 1
            if self.calls in self.lose_on:
                self.workers[member] = self.spec.worker(**self.spec.kwargs)  # restarted without its state
                raise RoleWorkerLost(self.name, "killed")
        return super().submit(member, method, *args)


def toy_trial(rounds: int = 4) -> TrialSpec:
    settings = toy_method.ToySettings(rounds=rounds, steps=10)
    return TrialSpec("toy", "point_reach", settings, 0)


def runner(trial: TrialSpec, lose_on: set[int], method: str = "train", recoveries: int = 5) -> ProgramRunner:
    (spec,) = toy_method.ToyProgram.roles_for(trial, 1, {})
    return ProgramRunner(trial, {"trainer": LosingGroup(spec, method, lose_on)}, 1, recoveries=recoveries)


def losses(reports) -> list[float]:
    return [report.metrics["loss"] for report, _, _ in reports]


def test_progress_between_rounds_names_the_next_round_without_the_last_ones_text():
    trial = toy_trial()
    program = runner(trial, set())
    program.run_round(0)
    assert program.progress()["round"] == 1 and program.progress()["text"] == ""


def test_a_worker_lost_mid_round_is_recovered_and_the_trial_ends_as_if_unharmed():
    trial = toy_trial()
    clean = runner(trial, set())
    expected = [clean.run_round(i) for i in range(4)]
    # Lost on the third training call (round 2), and once more on the retry of that round.
    harmed = runner(trial, {3, 4})
    got = [harmed.run_round(i) for i in range(4)]
    assert losses(got) == losses(expected)
    assert [len(recovered) for _, _, recovered in got] == [0, 0, 2, 0]
    assert "a worker of role 'trainer' was lost: killed" in got[2][2][0]
    assert [r.metrics["weights_version"] for r, _, _ in got] == [1.0, 2.0, 3.0, 4.0]  # the state came back
    assert harmed.recoveries_left == 3


def test_a_worker_lost_in_the_first_round_restarts_from_the_fresh_program():
    trial = toy_trial(rounds=2)
    expected = [runner(trial, set()).run_round(0)]
    got = [runner(trial, {1}).run_round(0)]
    assert losses(got) == losses(expected)


def test_a_worker_lost_while_the_state_is_gathered_is_recovered_too():
    trial = toy_trial(rounds=2)
    clean = runner(trial, set())
    expected = [clean.run_round(0), clean.run_round(1)]
    harmed = runner(trial, {2}, method="state_dict")  # the 1st state_dict is the fresh program's
    got = [harmed.run_round(0), harmed.run_round(1)]
    assert losses(got) == losses(expected) and len(got[0][2]) == 1


def test_without_recoveries_left_the_loss_is_handed_on():
    harmed = runner(toy_trial(), {1}, recoveries=0)
    with pytest.raises(RoleWorkerLost, match="trainer"):
        harmed.run_round(0)


def test_a_round_that_fails_after_a_recovery_carries_the_recovery_to_the_driver():
    """Recovered once, lost again with no recovery left: the error says what was recovered before it, and the
    driver's classification passes that on, so the first loss is recorded and counted too."""
    from orchestrator.failures import LOST_PROCESS, classify

    harmed = runner(toy_trial(), {3, 4}, recoveries=1)  # both losses in round 2
    harmed.run_round(0), harmed.run_round(1)
    with pytest.raises(RoleWorkerLost) as lost:
        harmed.run_round(2)
    failure = classify(pickle.loads(pickle.dumps(lost.value)))  # as it reaches the driver from the runner's process
    assert failure.kind == LOST_PROCESS and len(failure.recovered) == 1
    assert "a worker of role 'trainer' was lost: killed" in failure.recovered[0]


def test_a_loss_whose_restore_fails_is_handed_on_once_not_also_as_recovered(monkeypatch):
    """The runner could not hand the restarted worker its state: that loss is the round's error (the driver
    records it as the attempt's failure), not a recovery too."""
    from orchestrator.failures import LOST_PROCESS, classify
    from workers import actors

    class NeverRestored(LosingGroup):
        def submit(self, member: int, method: str, *args):
            if method == "load_state_dict":
                raise RoleWorkerLost(self.name, "still restarting")
            return super().submit(member, method, *args)

    monkeypatch.setattr(actors, "RESTART_PAUSES", (0.0, 0.0))
    trial = toy_trial()
    (spec,) = toy_method.ToyProgram.roles_for(trial, 1, {})
    harmed = ProgramRunner(trial, {"trainer": NeverRestored(spec, "train", {1})}, 1, recoveries=5)
    with pytest.raises(RoleWorkerLost) as lost:
        harmed.run_round(0)
    failure = classify(pickle.loads(pickle.dumps(lost.value)))
    assert failure.kind == LOST_PROCESS and failure.recovered == () and failure.role == "trainer"
    assert harmed.recoveries_left == 5


def test_a_memory_kill_whose_restore_fails_is_still_a_memory_kill(monkeypatch):
    """The restore's own error ("still restarting") must not replace the loss's words: the driver's advice for a
    memory kill (fewer trials at once, fewer threads) hangs on them."""
    from orchestrator.failures import classify
    from workers import actors

    class KilledForMemory(LocalRoleGroup):
        def submit(self, member: int, method: str, *args):
            if method == "train":
                raise RoleWorkerLost(self.name, "the worker was killed due to the node running low on memory")
            if method == "load_state_dict":
                raise RoleWorkerLost(self.name, "ActorUnavailableError: restarting")
            return super().submit(member, method, *args)

    monkeypatch.setattr(actors, "RESTART_PAUSES", (0.0,))
    trial = toy_trial()
    (spec,) = toy_method.ToyProgram.roles_for(trial, 1, {})
    group = KilledForMemory(spec.name, [spec.worker(**spec.kwargs)])
    harmed = ProgramRunner(trial, {"trainer": group}, 1, recoveries=5)
    with pytest.raises(RoleWorkerLost) as lost:
        harmed.run_round(0)
    failure = classify(pickle.loads(pickle.dumps(lost.value)))
    assert failure.memory and "restoring its state failed" in str(lost.value) and failure.role == "trainer"


def test_a_round_that_fails_without_a_recovery_carries_none():
    from orchestrator.failures import classify

    with pytest.raises(RoleWorkerLost) as lost:
        runner(toy_trial(), {1}, recoveries=0).run_round(0)
    assert classify(lost.value).recovered == ()


def test_the_lost_process_backoff_grows_until_a_round_completes():
    """Losses without progress back off longer each time; a completed round starts the backoff over."""
    from orchestrator.scheduler import BACKOFF_SECONDS, TrialState

    state = TrialState(trial=None, total_rounds=3)
    assert [state.backoff() for _ in range(6)] == [*BACKOFF_SECONDS, BACKOFF_SECONDS[-1]]
    state.progressed()
    assert state.backoff() == BACKOFF_SECONDS[0]


RAY_UNEXPECTED_EXIT = (
    "The actor died unexpectedly before finishing this task.\n\tclass_name: ProgramRunner\n"
    "The actor is dead because its worker process has died. Worker exit type: SYSTEM_ERROR Worker exit detail: "
    "Worker unexpectedly exits with a connection error code 2. End of file. Some common causes include: (1) the "
    "process was killed by the OOM killer due to high memory usage, (2) ray stop --force was called, or (3) the "
    "worker crashed unexpectedly due to SIGSEGV or another unexpected error."
)


@pytest.mark.parametrize(
    ("text", "memory"),
    [
        (RAY_UNEXPECTED_EXIT, False),  # a SIGKILL or a crash: Ray lists the OOM killer among its possible causes
        ("Task was killed due to the node running low on memory. Memory on the node was 20 GB used / 24 GB", True),
    ],
)
def test_only_a_kill_for_memory_is_reported_as_one(text, memory):
    from orchestrator.failures import LOST_PROCESS, classify

    failure = classify(RoleWorkerLost("trainer", f"ActorDiedError: {text}"))
    assert failure.kind == LOST_PROCESS and failure.memory is memory
    assert ("killed for memory" in failure.cause) is memory
