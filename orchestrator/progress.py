"""Live progress of a sweep on the terminal."""

from __future__ import annotations

import shutil
import sys
import time
from typing import TextIO

from orchestrator.scheduler import SweepState


def _clock(seconds: float | None) -> str:
    if seconds is None:
        return "?"
    seconds = int(seconds)
    hours, rest = divmod(seconds, 3600)
    minutes, seconds = divmod(rest, 60)
    return f"{hours}:{minutes:02d}:{seconds:02d}" if hours else f"{minutes}:{seconds:02d}"


def describe(state: SweepState) -> str:
    """One line: counts, the running trials' episode and step, elapsed time and ETA."""
    running = "; ".join(
        f"{label} ep {(p.get('episode') or 0) + 1}/{episodes} step {p['step']}/{p['steps']}"
        if p.get("episode") is not None
        else f"{label} starting"
        for label, episodes, p in state.running
    )
    counts = f"{state.name}: {state.done}/{state.total} done, {len(state.running)} running, {state.failed} failed"
    timing = f"elapsed {_clock(state.elapsed)}, ETA {_clock(state.eta)}"
    return f"{counts} | {running or 'idle'} | {timing}"


class ProgressDisplay:
    """Rewrites one status line on a terminal; prints a line every ``interval`` seconds otherwise."""

    def __init__(self, stream: TextIO = sys.stderr, interval: float = 10.0):
        self.stream = stream
        self.interactive = hasattr(stream, "isatty") and stream.isatty()
        self.interval = interval
        self._last_print = 0.0
        self._last_counts: tuple[int, int] | None = None

    def __call__(self, state: SweepState) -> None:
        line = describe(state)
        if self.interactive:
            width = shutil.get_terminal_size((120, 20)).columns
            self.stream.write("\r\x1b[2K" + line[: width - 1])
            self.stream.flush()
            return
        counts = (state.done, state.failed)
        now = time.monotonic()
        if counts != self._last_counts or now - self._last_print >= self.interval:
            self._last_counts, self._last_print = counts, now
            print(line, file=self.stream, flush=True)

    def close(self) -> None:
        if self.interactive:
            self.stream.write("\n")
            self.stream.flush()
