"""Clean shutdown of long-running processes: the registry service and the runtime and learner workers.

Invariants:
1. While :func:`stop_on_signals` is active in the main thread, SIGTERM and SIGINT set every
   given event and do nothing else; the handlers in force before are restored on exit.
2. Outside the main thread (Python only delivers signals there) or when disabled, it changes
   nothing.
"""

from __future__ import annotations

import contextlib
import logging
import signal
import threading
from collections.abc import Iterator
from types import FrameType

log = logging.getLogger(__name__)


@contextlib.contextmanager
def stop_on_signals(*events: threading.Event, enabled: bool = True, what: str = "process") -> Iterator[None]:
    """While active, SIGTERM and SIGINT set each of ``events`` so the owner can wind down cleanly.

    Args:
        events: Set on the first signal.
        enabled: False leaves the signal handlers alone (embedded use, tests).
        what: Named in the log line ("registry", "runtime worker", ...).
    """
    if not enabled or threading.current_thread() is not threading.main_thread():
        yield
        return

    def on_signal(signum: int, frame: FrameType | None) -> None:
        log.info("received %s; shutting down the %s", signal.Signals(signum).name, what)
        for event in events:
            event.set()

    previous = {sig: signal.signal(sig, on_signal) for sig in (signal.SIGTERM, signal.SIGINT)}
    try:
        yield
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
