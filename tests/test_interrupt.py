"""Stop signals (Ctrl-C, SIGTERM, SIGHUP) in the driver loop (orchestrator/interrupt.py), without Ray."""

from __future__ import annotations

import signal
import threading

import pytest

from orchestrator.interrupt import STOP_SIGNALS, InterruptRequest, Interrupted, describe


@pytest.fixture(autouse=True)
def default_dispositions():
    """Each test starts from Python's defaults, whatever the test run inherited (nohup ignores SIGHUP; a shell
    without job control starts background commands with SIGINT ignored)."""
    defaults = {signal.SIGINT: signal.default_int_handler, signal.SIGTERM: signal.SIG_DFL}
    defaults[signal.SIGHUP] = signal.SIG_DFL
    inherited = {signum: signal.signal(signum, handler) for signum, handler in defaults.items()}
    yield
    for signum, handler in inherited.items():
        signal.signal(signum, handler)


def library_call_that_swallows_keyboard_interrupt():
    """What Ray's core worker does when Ctrl-C lands in a wait that then returns normally."""
    try:
        signal.raise_signal(signal.SIGINT)
    except KeyboardInterrupt:
        pass


def test_ctrl_c_is_recorded_until_the_loop_asks():
    with InterruptRequest() as interrupt:
        interrupt.raise_if_requested()  # nothing pressed yet
        library_call_that_swallows_keyboard_interrupt()
        assert interrupt.requested
        with pytest.raises(KeyboardInterrupt):
            interrupt.raise_if_requested()


def test_second_ctrl_c_raises_at_once():
    with InterruptRequest():
        signal.raise_signal(signal.SIGINT)
        with pytest.raises(KeyboardInterrupt):
            signal.raise_signal(signal.SIGINT)


def test_previous_handler_is_restored():
    before = signal.getsignal(signal.SIGINT)
    with InterruptRequest():
        assert signal.getsignal(signal.SIGINT) is not before
    assert signal.getsignal(signal.SIGINT) is before


def test_outside_the_main_thread_signals_are_left_alone():
    before = signal.getsignal(signal.SIGINT)
    seen = []

    def enter():
        with InterruptRequest() as interrupt:
            seen.append((signal.getsignal(signal.SIGINT), interrupt.requested))

    thread = threading.Thread(target=enter)
    thread.start()
    thread.join()
    assert seen == [(before, None)]


@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGHUP])
def test_sigterm_and_sighup_are_stop_requests_like_ctrl_c(signum):
    """Without this, ray.init's SIGTERM handler calls sys.exit: the SystemExit passes the code that closes the
    sweep's runs, which would stay RUNNING."""
    with InterruptRequest() as interrupt:
        signal.raise_signal(signum)
        assert interrupt.requested == signum
        with pytest.raises(Interrupted) as stop:
            interrupt.raise_if_requested()
        assert stop.value.signum == signum and describe(stop.value) == signal.Signals(signum).name
        with pytest.raises(Interrupted):  # sent again: at once
            signal.raise_signal(signum)


def test_ctrl_c_is_described_as_ctrl_c_and_every_previous_handler_is_restored():
    assert describe(KeyboardInterrupt()) == "Ctrl-C" == describe(Interrupted(signal.SIGINT))
    before = {signum: signal.getsignal(signum) for signum in STOP_SIGNALS}
    with InterruptRequest():
        assert all(signal.getsignal(signum) is not before[signum] for signum in STOP_SIGNALS)
    assert {signum: signal.getsignal(signum) for signum in STOP_SIGNALS} == before


def test_a_signal_the_process_ignores_stays_ignored():
    """nohup ignores SIGHUP: a closed terminal must not stop the sweep it was started to outlive."""
    previous = signal.signal(signal.SIGHUP, signal.SIG_IGN)
    try:
        with InterruptRequest() as interrupt:
            assert signal.getsignal(signal.SIGHUP) is signal.SIG_IGN
            signal.raise_signal(signal.SIGHUP)
            assert interrupt.requested is None
    finally:
        signal.signal(signal.SIGHUP, previous)


def test_ctrl_c_is_handled_even_where_the_shell_ignored_it():
    """A shell without job control starts background commands with SIGINT ignored; ``kill -INT`` must still stop
    such a driver cleanly."""
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        with InterruptRequest() as interrupt:
            signal.raise_signal(signal.SIGINT)
            assert interrupt.requested == signal.SIGINT
        assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN
    finally:
        signal.signal(signal.SIGINT, previous)
