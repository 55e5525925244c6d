"""Ctrl-C for a driver that spends its time inside Ray calls.

Python turns SIGINT into KeyboardInterrupt at the next bytecode, but while the
driver waits in ``ray.wait`` Ray's core worker polls for signals itself and
converts the KeyboardInterrupt into a status that it drops when the wait
returns for another reason (a result arrived, the timeout passed). The signal
is then gone and the sweep carries on. :class:`InterruptRequest` records
Ctrl-C in a flag instead, which no library can swallow, and the scheduler's
loop turns it into KeyboardInterrupt at a point of its choosing.
"""

from __future__ import annotations

import signal
import threading
from types import FrameType


class InterruptRequest:
    """Context manager: SIGINT sets :attr:`requested`; a second SIGINT raises at once.

    Outside the main thread signal handlers cannot be installed; there it
    leaves the default behaviour alone.
    """

    def __init__(self) -> None:
        self.requested = False
        self._previous = None
        self._installed = False

    def __enter__(self) -> InterruptRequest:
        if threading.current_thread() is threading.main_thread():
            self._previous = signal.signal(signal.SIGINT, self._handle)
            self._installed = True
        return self

    def __exit__(self, *exc) -> None:
        if self._installed:
            signal.signal(signal.SIGINT, self._previous)
            self._installed = False

    def _handle(self, signum: int, frame: FrameType | None) -> None:
        if self.requested:  # pressed again: the user does not want to wait for the next check
            raise KeyboardInterrupt
        self.requested = True

    def raise_if_requested(self) -> None:
        """Raise KeyboardInterrupt if Ctrl-C was pressed since entering the context."""
        if self.requested:
            raise KeyboardInterrupt
