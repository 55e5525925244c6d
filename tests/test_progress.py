"""The sweep's progress line on a terminal, and notes printed while it is shown."""

from __future__ import annotations

import io

from orchestrator.progress import ProgressDisplay, describe
from orchestrator.scheduler import SweepState


class Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


STATE = SweepState(
    name="fetch",
    total=3,
    done=1,
    failed=0,
    running=[("noisy_fetch/pets/s0", {"phase": "running", "round": 6, "rounds": 20, "text": "step 12/50"})],
    elapsed=3725.0,
    eta=600.0,
)


def test_the_line_shows_counts_each_running_trials_place_and_the_time_to_go():
    assert describe(STATE) == (
        "fetch: 1/3 done, 1 running, 0 failed | noisy_fetch/pets/s0 round 7/20 step 12/50 | "
        "elapsed 1:02:05, ETA 10:00"
    )


def test_a_restoring_trial_names_the_checkpoints_round():
    restoring = STATE._replace(running=[("bridge_maze/s4", {"phase": "restoring", "round": 41, "rounds": 45})])
    assert "bridge_maze/s4 restoring from the checkpoint after round 42/45 |" in describe(restoring)


def test_a_note_on_a_terminal_clears_the_status_line_and_keeps_a_line_of_its_own():
    terminal = Terminal()
    display = ProgressDisplay(terminal)
    display(STATE)
    display.note("trial x continues with 1 thread")
    display(STATE)
    written = terminal.getvalue()
    status = "\r\x1b[2K" + describe(STATE)
    assert written == status + "\r\x1b[2K" + "icemlab: note: trial x continues with 1 thread\n" + status


def test_a_note_in_a_log_is_a_plain_line():
    log = io.StringIO()
    display = ProgressDisplay(log)
    display(STATE)
    display.note("resumed")
    assert log.getvalue() == describe(STATE) + "\nicemlab: note: resumed\n"


def test_the_eta_weighs_the_rounds_to_go_by_their_work():
    """A trial resumed after round 0 and 39 one-episode iterations has done half an iteration's work of its
    session in 30 s, a minute per unit of work; what remains (half of iteration 40, three frozen rows of 13
    episodes each) is 39.5 minutes away, and a trial without recorded work counts its rounds alike."""
    from orchestrator.scheduler import TrialState, time_to_go

    mbrl = TrialState(trial=None, total_rounds=44, round_work=(0.0,) + (1.0,) * 40 + (13.0,) * 3, rounds_done=40)
    at_start = mbrl.work_until(mbrl.rounds_done)
    assert time_to_go([mbrl], {}, at_start, elapsed=30.0) is None  # nothing done in this session yet
    seconds = time_to_go([mbrl], {id(mbrl): 0.5}, at_start, elapsed=30.0)
    assert seconds == 60.0 * (0.5 + 39.0)
    plain = TrialState(trial=None, total_rounds=10, rounds_done=4)
    assert time_to_go([plain], {id(plain): 0.5}, 4.0, elapsed=30.0) == 60.0 * 5.5
    assert plain.work_until(10.7) == 10.0 and mbrl.work_until(44.2) == 40.0 + 39.0  # never past the last round


def test_round_weights_that_do_not_fit_the_rounds_count_them_alike():
    from orchestrator.scheduler import checked_round_work

    assert checked_round_work([0, 1, 13], 3) == (0.0, 1.0, 13.0)
    assert checked_round_work([1, 1], 5) == () and checked_round_work([1, -1], 2) == ()
    assert checked_round_work([1, float("nan")], 2) == ()
