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
from workers.methods.base import Progress, RoleGroup, RoundReport, TrialSpec


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


class CheckpointMismatchError(ValueError):
    """A checkpoint written by another trial (method, task or seed differ)."""


class ProgramRunner:
    """Runs the rounds of one trial's program.

    Args:
        trial: the trial.
        roles: a role group per role the program declared.
        cpus: CPUs this process holds.
        expected_code: the driver's :func:`workers.code_fingerprint`; a mismatch is refused.
    """

    def __init__(self, trial: TrialSpec, roles: dict[str, RoleGroup], cpus: int = 1, expected_code: str | None = None):
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

    def restore(self, data: bytes) -> int:
        """Continue from a checkpoint written by :meth:`run_round`; returns the next round's index."""
        tree = checkpoint.from_bytes(data)
        identity = tree.get("trial", {})
        expected = {"method": self.trial.method, "task": self.trial.task, "seed": self.trial.seed}
        if {k: identity.get(k) for k in expected} != expected:
            raise CheckpointMismatchError(f"checkpoint of trial {identity} does not belong to this trial {expected}")
        self.program.load_state_dict(tree["program"])
        self.next_round = int(tree["next_round"])
        return self.next_round

    def run_round(self, index: int) -> tuple[RoundReport, bytes]:
        """Run round ``index`` (the next one); return its report and a checkpoint of the state after it."""
        if index != self.next_round:
            raise RuntimeError(f"asked for round {index}, but the program is at round {self.next_round}")
        started = time.perf_counter()
        report = self.program.run_round(index)
        report = report._replace(seconds=time.perf_counter() - started)
        self.next_round = index + 1
        state = {
            "trial": {"method": self.trial.method, "task": self.trial.task, "seed": self.trial.seed},
            "next_round": self.next_round,
            "code": code_fingerprint(),
            "program": self.program.state_dict(),
        }
        return report, checkpoint.to_bytes(state)

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
