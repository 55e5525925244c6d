"""Trial runners that misbehave on purpose, for the fault tests (shipped to Ray workers by value)."""

from __future__ import annotations

from workers.actors import TrialRunner


class FailingRunner(TrialRunner):
    """Raises in every episode of trials with seed 1."""

    def run_episode(self, episode: int):
        if self.seed == 1:
            raise RuntimeError("injected failure: seed 1 always raises")
        return super().run_episode(episode)
