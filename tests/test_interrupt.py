"""Ctrl-C handling of the driver loop (orchestrator/interrupt.py), without Ray."""

from __future__ import annotations

import signal
import threading

import pytest

from orchestrator.interrupt import InterruptRequest


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
    assert seen == [(before, False)]
