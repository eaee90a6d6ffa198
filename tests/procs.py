"""Stopping real child processes in tests."""

from __future__ import annotations

import signal
import subprocess


def terminate(proc: subprocess.Popen[str], timeout: float) -> int:
    """SIGTERM and wait up to ``timeout`` s, then SIGKILL; the exit code (negative for a signal)."""
    if proc.poll() is None:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
    return int(proc.returncode)


def kill(proc: subprocess.Popen[str]) -> None:
    """SIGKILL: no handler runs, nothing is flushed or closed."""
    if proc.poll() is None:
        proc.send_signal(signal.SIGKILL)
        proc.wait()
