"""Signals held while a frame is processed: delivered as the block ends, to the handler in place before it."""

from __future__ import annotations

import os
import signal
import threading

import pytest

from vtr.errors import Terminated
from vtr.signals import held_signals, sigterm_as_exception


def test_ctrl_c_is_delivered_when_the_block_ends():
    before = signal.getsignal(signal.SIGINT)
    done = []
    with pytest.raises(KeyboardInterrupt):
        with held_signals():
            os.kill(os.getpid(), signal.SIGINT)
            done.extend(range(1000))  # runs to the end: the signal is held
    assert len(done) == 1000
    assert signal.getsignal(signal.SIGINT) is before


def test_sigterm_is_delivered_as_terminated_within_sigterm_as_exception():
    done = []
    with pytest.raises(Terminated), sigterm_as_exception():
        with held_signals():
            os.kill(os.getpid(), signal.SIGTERM)
            done.append(1)
        done.append(2)  # not reached: delivered as the held block ended
    assert done == [1]


def test_only_the_first_signal_is_delivered_and_nothing_without_one():
    with sigterm_as_exception():
        with pytest.raises(Terminated):
            with held_signals():
                os.kill(os.getpid(), signal.SIGTERM)
                os.kill(os.getpid(), signal.SIGINT)
        with held_signals():
            pass  # no signal: no exception


def test_an_error_in_the_block_comes_out_as_the_context_of_the_signal():
    with pytest.raises(KeyboardInterrupt) as info:
        with held_signals():
            os.kill(os.getpid(), signal.SIGINT)
            raise ValueError("frame 3 is corrupt")
    assert isinstance(info.value.__context__, ValueError)


def test_outside_the_main_thread_nothing_is_held():
    seen = []

    def work():
        with held_signals():
            seen.append(signal.getsignal(signal.SIGINT))

    t = threading.Thread(target=work)
    t.start()
    t.join()
    assert seen == [signal.getsignal(signal.SIGINT)]  # handlers untouched (only the main thread may set them)
