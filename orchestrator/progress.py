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


def _trial_progress(label: str, progress: dict) -> str:
    phase = progress.get("phase")
    if phase == "placing":
        return f"{label} waiting for CPUs"
    if phase == "restoring":
        return f"{label} restoring from the checkpoint after round {progress['round'] + 1}/{progress['rounds']}"
    text = progress.get("text")
    where = f"round {progress['round'] + 1}/{progress['rounds']}"
    return f"{label} {where}" + (f" {text}" if text and text != "starting" else "")


def describe(state: SweepState) -> str:
    """One line: counts, each running trial's round and place within it, elapsed time and ETA."""
    running = "; ".join(_trial_progress(label, progress) for label, progress in state.running)
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

    def note(self, message: str) -> None:
        """Print a note on a line of its own; a terminal's status line is redrawn at the next update."""
        if self.interactive:
            self.stream.write("\r\x1b[2K")
        self.stream.write(f"icemlab: note: {message}\n")
        self.stream.flush()

    def close(self) -> None:
        if self.interactive:
            self.stream.write("\n")
            self.stream.flush()
