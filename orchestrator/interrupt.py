"""Ctrl-C, and the signals a supervisor stops a driver with, for a driver that spends its time inside Ray calls.

Python turns SIGINT into KeyboardInterrupt at the next bytecode, but while the
driver waits in ``ray.wait`` Ray's core worker polls for signals itself and
converts the KeyboardInterrupt into a status that it drops when the wait
returns for another reason (a result arrived, the timeout passed). The signal
is then gone and the sweep carries on. :class:`InterruptRequest` records
the signal in a flag instead, which no library can swallow, and the scheduler's
loop turns it into :class:`Interrupted` (a KeyboardInterrupt) at a point of its
choosing, where it knows which runs to close.

SIGTERM (``kill``, ``ray job stop``, a pod's eviction, ``timeout``) and SIGHUP
(the terminal closed) take the same path. Without it, ``ray.init``'s own SIGTERM
handler calls ``sys.exit``, whose SystemExit passes every handler that closes
the runs: the sweep and its trials would stay RUNNING with no cause recorded.
A SIGHUP the process was told to ignore (``nohup``) stays ignored. SIGINT is
handled even where it was ignored: a shell without job control starts
background commands with SIGINT ignored, and ``kill -INT`` is still how such a
driver is stopped cleanly.
"""

from __future__ import annotations

import signal
import threading
from types import FrameType

STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)
"""The signals that stop a driver cleanly: its runs closed KILLED, the trials continued by ``--resume``."""


class Interrupted(KeyboardInterrupt):
    """A stop signal, turned into an exception where the driver can close its runs."""

    def __init__(self, signum: int = signal.SIGINT) -> None:
        super().__init__(signal.Signals(signum).name)
        self.signum = signum


def describe(stop: KeyboardInterrupt) -> str:
    """``Ctrl-C`` for SIGINT (or a KeyboardInterrupt raised by Python itself), else the signal's name."""
    signum = getattr(stop, "signum", signal.SIGINT)
    return "Ctrl-C" if signum == signal.SIGINT else signal.Signals(signum).name


class InterruptRequest:
    """Context manager: a stop signal sets :attr:`requested`; a second one raises :class:`Interrupted` at once.

    Outside the main thread signal handlers cannot be installed; there it
    leaves the default behaviour alone.
    """

    def __init__(self) -> None:
        self.requested: int | None = None
        """The first stop signal received, or None."""
        self._previous: dict[int, object] = {}

    def __enter__(self) -> InterruptRequest:
        if threading.current_thread() is threading.main_thread():
            for signum in STOP_SIGNALS:
                if signum == signal.SIGHUP and signal.getsignal(signum) is signal.SIG_IGN:
                    continue  # nohup: the driver was started to outlive its terminal
                self._previous[signum] = signal.signal(signum, self._handle)
        return self

    def __exit__(self, *exc) -> None:
        for signum, previous in self._previous.items():
            signal.signal(signum, previous)
        self._previous = {}

    def _handle(self, signum: int, frame: FrameType | None) -> None:
        if self.requested is not None:  # sent again: the sender does not want to wait for the next check
            raise Interrupted(signum)
        self.requested = signum

    def raise_if_requested(self) -> None:
        """Raise :class:`Interrupted` if a stop signal arrived since entering the context."""
        if self.requested is not None:
            raise Interrupted(self.requested)
