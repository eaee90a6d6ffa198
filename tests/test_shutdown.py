from __future__ import annotations

import os
import signal
import threading

import pytest

from capevo.shutdown import stop_on_signals


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_inv1_signal_sets_every_event_and_previous_handlers_come_back(sig: signal.Signals) -> None:
    before = signal.getsignal(sig)
    first, second = threading.Event(), threading.Event()
    with stop_on_signals(first, second, what="test"):
        assert signal.getsignal(sig) is not before
        os.kill(os.getpid(), sig)
        assert first.wait(5) and second.wait(5)
    assert signal.getsignal(sig) is before


def test_inv2_disabled_or_off_the_main_thread_changes_nothing() -> None:
    before = signal.getsignal(signal.SIGTERM)
    with stop_on_signals(threading.Event(), enabled=False):
        assert signal.getsignal(signal.SIGTERM) is before
    seen: list[object] = []

    def off_main() -> None:
        with stop_on_signals(threading.Event()):
            seen.append(signal.getsignal(signal.SIGTERM))

    thread = threading.Thread(target=off_main)
    thread.start()
    thread.join()
    assert seen == [before]
