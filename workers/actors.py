"""What runs inside the service's Ray actors, as plain classes.

The scheduler turns these classes into actors with ``ray.remote``; here they
import neither Ray nor MLflow, so they are unit-tested like any other code.

* :class:`ProgramRunner` hosts one trial's program (workers/methods): it runs
  the rounds, and hands back each round's report with a checkpoint of the
  program's state, or continues from such a checkpoint.

The roles' workers (simulation in workers/simulation.py, DAgger relabeling,
ensemble training, distance-net updates) are classes of their own modules,
built in actors the same way.
"""

from __future__ import annotations

import os
import platform
import resource
import sys
import time
from typing import Any

from workers import checkpoint, code_fingerprint
from workers.methods.base import Progress, RoleGroup, RoleWorkerLost, RoundReport, TrialSpec


def use_cpus(cpus: float) -> None:
    """Size torch's thread pool to the CPUs this process holds (when torch is in use)."""
    if "torch" in sys.modules:
        import torch

        torch.set_num_threads(max(1, int(cpus)))


def machine_info() -> dict[str, str]:
    """CPU model, the CPUs this process may use, and the host name."""
    model = platform.processor() or platform.machine()
    try:
        for line in open("/proc/cpuinfo"):
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    try:
        cpus = len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        cpus = os.cpu_count() or 1
    return {"cpu_model": model, "cpus": str(cpus), "host": platform.node()}


def rss_mb() -> float | None:
    """Resident memory of this process now (Linux), for memory-kill reports."""
    try:
        with open("/proc/self/statm") as statm:
            return int(statm.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20
    except (OSError, ValueError, IndexError):
        return None


RESTART_PAUSES = (0.2, 0.5, 1.0, 2.0, 4.0, 8.0, 15.0)
"""Seconds to wait before each try to hand a restarted worker its state (about 30 s in all)."""


class CheckpointMismatchError(ValueError):
    """A checkpoint written by another trial (method, task or seed differ)."""


class CheckpointFromOtherCodeError(RuntimeError):
    """A checkpoint written by other icemlab code that this code's program cannot load (a code error: every
    attempt with this code fails alike, and an earlier checkpoint of the same code would fail too)."""


RECOVERED_ATTRIBUTE = "recovered_in_round"
"""Set on an error that ends a round after role workers were recovered in it: their causes (list of str), so the
driver records those recoveries and counts them against the budget as it does a finished round's."""


class ProgramRunner:
    """Runs the rounds of one trial's program.

    A stateful role worker lost during a round (:class:`RoleWorkerLost`) costs that round only: the runner
    keeps the checkpoint of the last completed round, restores the program from it (which hands the
    restarted worker its state again) and runs the round again, up to ``recoveries`` times over the
    attempt; each recovery is reported with the round's result, or, if the round fails after all, on its
    error (:data:`RECOVERED_ATTRIBUTE`).

    Args:
        trial: the trial.
        roles: a role group per role the program declared.
        cpus: CPUs this process holds.
        expected_code: the driver's :func:`workers.code_fingerprint`; a mismatch is refused.
        recoveries: role workers this runner may recover in place (the trial's lost-process budget).
    """

    def __init__(
        self,
        trial: TrialSpec,
        roles: dict[str, RoleGroup],
        cpus: int = 1,
        expected_code: str | None = None,
        recoveries: int = 0,
    ):
        if expected_code is not None and expected_code != code_fingerprint():
            raise RuntimeError(
                f"this node runs different icemlab code (fingerprint {code_fingerprint()}) than the driver "
                f"({expected_code}); install the same icemlab on every node (see deploy/Dockerfile)"
            )
        from workers.methods import METHODS

        self.trial = trial
        self.program = METHODS[trial.method](trial, roles, cpus)
        use_cpus(cpus)
        self.next_round = 0
        self.recoveries_left = recoveries
        self._last_state: bytes | None = None  # the program after the last completed round, as a checkpoint

    def restore(self, data: bytes) -> int:
        """Continue from a checkpoint written by :meth:`run_round`; returns the next round's index."""
        tree = checkpoint.from_bytes(data)
        identity = tree.get("trial", {})
        expected = {"method": self.trial.method, "task": self.trial.task, "seed": self.trial.seed}
        if {k: identity.get(k) for k in expected} != expected:
            raise CheckpointMismatchError(f"checkpoint of trial {identity} does not belong to this trial {expected}")
        try:
            self.program.load_state_dict(tree["program"])
        except RoleWorkerLost:
            raise
        except Exception as error:
            written_by = tree.get("code")
            if written_by is None or written_by == code_fingerprint():
                raise
            raise CheckpointFromOtherCodeError(
                f"the checkpoint before round {tree.get('next_round')} was written by other icemlab code "
                f"(fingerprint {written_by}; this code is {code_fingerprint()}), and this code cannot load it "
                f"({type(error).__name__}: {error}); resume with the icemlab that wrote it"
            ) from error
        self.next_round = int(tree["next_round"])
        self._last_state = data
        return self.next_round

    def run_round(self, index: int) -> tuple[RoundReport, bytes, list[str]]:
        """Run round ``index`` (the next one).

        Returns its report, a checkpoint of the state after it, and the causes of the role workers
        recovered in place during it (see the class docstring).
        """
        if index != self.next_round:
            raise RuntimeError(f"asked for round {index}, but the program is at round {self.next_round}")
        if self._last_state is None:  # a fresh program: its state before round 0 is where a recovery restarts
            self._last_state = self._checkpoint(index)
        recovered: list[str] = []
        started = time.perf_counter()
        try:
            while True:
                try:  # the round and the state after it (gathered from the stateful workers too)
                    report = self.program.run_round(index)
                    state = self._checkpoint(index + 1)
                    break
                except RoleWorkerLost as lost:
                    if self.recoveries_left <= 0:
                        raise
                    # Counted once restored: a restore that fails hands this same loss on as the round's error,
                    # and it must not also be reported as recovered.
                    try:
                        self._restore_last_round()
                    except RoleWorkerLost as failed:
                        # The loss's own words (a memory kill says so) with why it could not be recovered.
                        raise RoleWorkerLost(lost.role, f"{lost.cause}; restoring its state failed: {failed}") from None
                    self.recoveries_left -= 1
                    recovered.append(str(lost))
        except Exception as error:
            if recovered:
                setattr(error, RECOVERED_ATTRIBUTE, list(recovered))
            raise
        report = report._replace(seconds=time.perf_counter() - started)
        self.next_round = index + 1
        self._last_state = state
        # The finished round's last words would otherwise be shown under the next round's number.
        self.program.set_progress(0.0, "")
        return report, state, recovered

    def _restore_last_round(self) -> None:
        """Put the program (and through it, every stateful worker) back to the last completed round.

        The lost worker is being restarted; calls to it fail until it is up, so restoring is tried again
        after growing pauses before the loss is handed on.
        """
        state = checkpoint.from_bytes(self._last_state)["program"]
        for pause in RESTART_PAUSES:
            time.sleep(pause)
            try:
                self.program.load_state_dict(state)
                return
            except RoleWorkerLost as lost:
                failure = lost
        raise failure

    def _checkpoint(self, next_round: int) -> bytes:
        return checkpoint.to_bytes(
            {
                "trial": {"method": self.trial.method, "task": self.trial.task, "seed": self.trial.seed},
                "next_round": next_round,
                "code": code_fingerprint(),
                "program": self.program.state_dict(),
            }
        )

    def progress(self) -> dict[str, Any]:
        """The round under way and the program's progress within it (read while a round runs)."""
        current: Progress = self.program.progress()
        return {"round": self.next_round, "fraction": current.fraction, "text": current.text, "rss_mb": rss_mb()}

    def total_rounds(self) -> int:
        return self.program.total_rounds()

    def pid(self) -> int:
        """Process id (for fault-injection tests and diagnostics)."""
        return os.getpid()

    def machine(self) -> dict[str, str]:
        """The machine this trial runs on (recorded with its results)."""
        return machine_info()

    def peak_memory_mb(self) -> float:
        """Peak resident memory of this process."""
        return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024

    def close(self) -> None:
        self.program.close()
