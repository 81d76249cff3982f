"""Keeping a block from being cut short by a signal: the main job while it stops its children, a
recording while it saves what was recorded (docs/understand.md)."""

from __future__ import annotations

import contextlib
import signal
import threading
from typing import Iterator, Sequence, Set


@contextlib.contextmanager
def signals_deferred(signals: Sequence[int]) -> Iterator[Set[int]]:
    """Inside the block the given signals neither raise nor stop the process; the set it yields
    holds those that arrived, for the caller to act on afterwards. The previous handlers are back
    after the block. A signal that is ignored (SIGHUP under nohup, SIGINT of a background job) is
    left ignored and never counted: caught here, a terminal closed while a recording was saved
    marked it interrupted although nohup had asked for the hang-up to be ignored. Outside the main
    thread, where handlers cannot be set, the block runs unprotected (and the set stays empty)."""
    arrived: Set[int] = set()
    if threading.current_thread() is not threading.main_thread():
        yield arrived
        return
    previous = {s: signal.getsignal(s) for s in signals}
    previous = {s: h for s, h in previous.items() if h != signal.SIG_IGN}
    for s in previous:
        signal.signal(s, lambda signum, _frame: arrived.add(signum))
    try:
        yield arrived
    finally:
        for s, h in previous.items():
            signal.signal(s, h)
