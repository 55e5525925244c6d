"""Why a trial's attempt ended, in three classes that call for different responses.

* ``code_error``: the method's or task's code raised. Deterministic: a retry
  from the last checkpoint is worth it only a few times (``retries``), and an
  error that repeats identically is not retried again.
* ``lost_process``: an actor, its process or its node went away (SIGKILL, the
  kernel's or Ray's memory killer, a preempted node). Nothing is wrong with the
  code: the trial resumes from its last checkpoint, with backoff, under its own
  budget (``max_lost_processes``).
* ``bad_checkpoint``: the program refused a checkpoint read back from the
  store (corrupt, or not this trial's): the trial falls back to the one before.

An unreachable tracking server is the third kind of fault the issue names; the
MLflow client retries its requests itself, and the driver's logging waits.
"""

from __future__ import annotations

import re
import traceback
from typing import NamedTuple

CODE_ERROR = "code_error"
LOST_PROCESS = "lost_process"
BAD_CHECKPOINT = "bad_checkpoint"
INTERRUPTED = "interrupted"
"""Ctrl-C: the run ends KILLED and continues with ``--resume``."""
DRIVER_ERROR = "driver_error"
"""The driver itself raised (e.g. the tracking store failed): the runs end KILLED, the sweep FAILED."""
DRIVER_LOST = "driver_lost"
"""The driver ended without closing its runs (killed with SIGKILL, out of memory, its machine lost): recorded by
the ``--resume`` that finds them still RUNNING."""

_NODE_MEMORY = re.compile(r"was ([\d.]+\s*[KMGT]?i?B) used / ([\d.]+\s*[KMGT]?i?B) limit")
_MEMORY_WORDS = re.compile(r"out of memory|OutOfMemoryError|running low on memory|memory monitor", re.IGNORECASE)
"""Words of a kill for memory: Ray's memory monitor ("killed due to the node running low on memory"), its
OutOfMemoryError, a CUDA or Python "out of memory". Not "OOM" or "memory usage": every unexpected worker exit's
message lists "(1) the process was killed by the OOM killer due to high memory usage" among its common causes,
and a plain SIGKILL or crash would be reported as a kill for memory with advice to run fewer trials."""


class Failure(NamedTuple):
    """A classified failure of an attempt."""

    kind: str
    """code_error, lost_process or bad_checkpoint."""
    cause: str
    """One line for tags and the status command."""
    detail: str
    """The whole story: traceback or Ray's report."""
    signature: str
    """What identifies a repeat of the same error (exception type and traceback, without addresses)."""
    memory: bool = False
    """A memory kill (kernel OOM killer or Ray's memory monitor)."""
    recovered: tuple[str, ...] = ()
    """Causes of the role workers the runner recovered in the failed round before it failed (not yet recorded)."""
    role: str | None = None
    """The role whose worker's loss ended the attempt (None when it was not a role worker's, e.g. the runner's)."""


def classify(error: BaseException, memory_mb: float | None = None) -> Failure:
    """Classify an exception raised by ``ray.get`` on a trial's call (or by the driver's own handling).

    Args:
        memory_mb: the trial runner's resident memory when last seen, for memory kills.
    """
    import ray.exceptions as rex

    from workers.actors import RECOVERED_ATTRIBUTE, CheckpointMismatchError
    from workers.checkpoint import CheckpointError
    from workers.methods import RoleWorkerLost

    inner = error
    # A runner that got a dead worker's error re-raises it wrapped: look through the wrapping.
    while isinstance(inner, rex.RayTaskError) and isinstance(inner.cause, rex.RayError):
        inner = inner.cause
    cause_of_task = inner.cause if isinstance(inner, rex.RayTaskError) else inner
    recovered = tuple(getattr(cause_of_task, RECOVERED_ATTRIBUTE, ()))
    if isinstance(cause_of_task, CheckpointError | CheckpointMismatchError):
        return Failure(BAD_CHECKPOINT, _first_line(cause_of_task), _detail(error), _signature(error))
    if isinstance(cause_of_task, RoleWorkerLost):  # a role worker lost beyond what the runner could recover
        text = str(cause_of_task)
        memory = bool(_MEMORY_WORDS.search(text))
        cause = _lost_cause(cause_of_task, text, memory, memory_mb)
        return Failure(
            LOST_PROCESS, cause, _detail(error), _signature(cause_of_task), memory, recovered, cause_of_task.role
        )
    lost_types = (
        rex.ActorDiedError,
        rex.ActorUnavailableError,
        rex.WorkerCrashedError,
        rex.NodeDiedError,
        rex.ObjectLostError,
        rex.OutOfMemoryError,
        rex.RayActorError,
    )
    if isinstance(inner, lost_types) and not getattr(inner, "actor_init_failed", False):
        text = str(inner)
        memory = isinstance(inner, rex.OutOfMemoryError) or bool(_MEMORY_WORDS.search(text))
        cause = _lost_cause(inner, text, memory, memory_mb)
        return Failure(LOST_PROCESS, cause, text, _signature(inner), memory)
    detail = _detail(error)
    return Failure(CODE_ERROR, _code_cause(cause_of_task, detail), detail, _signature(error), recovered=recovered)


def _lost_cause(error: BaseException, text: str, memory: bool, memory_mb: float | None) -> str:
    name = type(error).__name__
    if memory:
        used = f"; it was last seen using {memory_mb:,.0f} MB" if memory_mb else ""
        node = _NODE_MEMORY.search(text)
        if node:
            used += f"; the node had {node[1]} of {node[2]} in use"
        return (
            f"{name}: a process was killed for memory{used}. Run fewer trials at once (--max-concurrent), "
            "give trials fewer threads (resources.threads_per_worker) or shrink the method's batch or buffer sizes"
        )
    preempted = " (node preempted)" if getattr(error, "preempted", False) else ""
    first = next((line.strip() for line in text.splitlines() if line.strip()), name)
    return f"{name}{preempted}: {first}"


def _code_cause(error: BaseException, detail: str) -> str:
    lines = [line for line in detail.strip().splitlines() if line.strip()]
    last = lines[-1].strip() if lines else ""
    return last or f"{type(error).__name__}: {error}"


_ANSI = re.compile(r"\x1b\[[0-9;]*m")


def _detail(error: BaseException) -> str:
    """The traceback as the process that raised saw it (Ray's task traceback), without terminal colours."""
    text = getattr(error, "traceback_str", None) or str(error)
    if not text.strip():
        text = "".join(traceback.format_exception(error))
    text = _ANSI.sub("", text)
    if "Traceback" not in text and 'File "' in text:
        text = "Traceback (most recent call last), in the trial's actor:\n" + text
    return text


def _first_line(error: BaseException) -> str:
    return (str(error).strip().splitlines() or [type(error).__name__])[0]


def _signature(error: BaseException) -> str:
    text = _detail(error)
    # Process ids, addresses and actor ids differ between repeats of the same error.
    text = re.sub(r"0x[0-9a-f]+|pid=\d+|ip=[\d.]+|[0-9a-f]{16,}", "", text)
    return f"{type(error).__name__}:{text}"
