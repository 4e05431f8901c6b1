"""Signals in a run: SIGTERM as an exception like Ctrl-C, and both held while a frame is processed.

Python raises ``KeyboardInterrupt`` (and, within :func:`sigterm_as_exception`, ``Terminated``) between any
two bytecodes. A frame's work (odometry, the keyframes it finalizes written to the map, its report rows)
interrupted half-way would lose keyframes that had left the odometry window but were not yet written, so
the run loops process each frame within :func:`held_signals`: a signal arriving then is delivered as the
frame ends, and an interrupted run ends with every keyframe it made written (``Teach.abort``).
"""

from __future__ import annotations

import signal
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from types import FrameType

from .errors import Terminated

HELD_SIGNALS = (signal.SIGINT, signal.SIGTERM)


def _raise_terminated(signum: int, frame: FrameType | None) -> None:
    raise Terminated()


def _in_main_thread() -> bool:
    return threading.current_thread() is threading.main_thread()


@contextmanager
def sigterm_as_exception() -> Iterator[None]:
    """Within the block SIGTERM raises ``Terminated`` (an orderly exit like Ctrl-C: ``with`` blocks
    close, runs in progress are recorded as aborted); the previous handler comes back after it.
    Only the main thread can handle signals (elsewhere this does nothing)."""
    if not _in_main_thread():
        yield
        return
    previous = signal.signal(signal.SIGTERM, _raise_terminated)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


@contextmanager
def held_signals() -> Iterator[None]:
    """Within the block Ctrl-C (SIGINT) and SIGTERM are held; the first one that arrived is delivered
    as the block ends, to the handler that was in place before it (raising ``KeyboardInterrupt`` or
    ``Terminated`` there, or the default action). Only the main thread can handle signals (elsewhere
    nothing is held)."""
    if not _in_main_thread():
        yield
        return
    held: list[int] = []

    def hold(signum: int, frame: FrameType | None) -> None:
        held.append(signum)

    previous: dict[int, object] = {int(s): signal.signal(s, hold) for s in HELD_SIGNALS}
    try:
        yield
    finally:
        for s, handler in previous.items():
            signal.signal(s, signal.SIG_DFL if handler is None else handler)  # type: ignore[arg-type]
        if held:
            _deliver(held[0], previous[held[0]])


def _deliver(signum: int, handler: object) -> None:
    """Act on ``signum`` as ``handler`` (a handler that ``signal.signal`` returned) would have."""
    if callable(handler):
        handler(signum, None)
    elif handler in (signal.SIG_DFL, None):
        signal.raise_signal(signum)  # the default action, now that the default is back
