"""Crash safety: a real writer process killed with SIGKILL, then recovered.

Writer invariant 2 and recover invariants 1-2. Assertions are on message counts reported by
the child, never on the parent's timing; the only deadlines are generous upper bounds.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from _trace_helpers import count_messages
from mcap.reader import make_reader

from capevo.runtime.traces import EnvStep, TraceReader, recover
from capevo.runtime.traces.scan import has_footer

CHILD = Path(__file__).with_name("_crash_child.py")


def start_child(path: Path, mode: str, interval: float, n: int = 0) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [sys.executable, str(CHILD), str(path), mode, str(interval), str(n)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


def read_line(child: subprocess.Popen[str]) -> str:
    assert child.stdout is not None
    line = child.stdout.readline()
    if not line:
        child.wait(timeout=10)
        err = child.stderr.read() if child.stderr else ""
        raise AssertionError(f"child exited with {child.returncode} before reporting: {err}")
    return line


def kill(child: subprocess.Popen[str]) -> None:
    os.kill(child.pid, signal.SIGKILL)
    child.wait(timeout=10)
    assert child.returncode == -signal.SIGKILL


def recovered_steps(src: Path, tmp_path: Path) -> list[int]:
    assert not has_footer(src)  # the kill left an unfinished file
    out = tmp_path / "recovered.mcap"
    report = recover(src, out)
    assert not report.complete
    assert report.messages == report.messages_by_topic.get("/env/step", 0)
    with out.open("rb") as f:  # the copy is a finished, standard MCAP
        summary = make_reader(f).get_summary()
    assert summary is not None and summary.statistics is not None
    assert summary.statistics.message_count == report.messages
    reader = TraceReader(out)
    assert reader.metadata().run_id == "crash"
    steps = [s.step for s in reader.records() if isinstance(s, EnvStep)]
    assert steps == list(range(len(steps)))  # a prefix of what was written, in order
    return steps


@pytest.mark.timeout(60)
def test_sigkill_after_explicit_flush_loses_nothing_flushed(tmp_path: Path) -> None:
    path = tmp_path / "run.mcap"
    child = start_child(path, "explicit", interval=3600.0, n=300)
    try:
        flushed = int(read_line(child))
    finally:
        kill(child)
    steps = recovered_steps(path, tmp_path)
    assert len(steps) >= flushed == 300


@pytest.mark.timeout(60)
def test_sigkill_of_an_idle_writer_keeps_what_the_timer_flushed(tmp_path: Path) -> None:
    # Nothing writes after the report: only the background flush can put the steps on disk.
    path = tmp_path / "run.mcap"
    child = start_child(path, "idle", interval=0.3, n=120)
    try:
        written = int(read_line(child))
        deadline = time.monotonic() + 20
        while count_messages(path) < written and time.monotonic() < deadline:
            time.sleep(0.05)
    finally:
        kill(child)
    assert len(recovered_steps(path, tmp_path)) >= written == 120


@pytest.mark.timeout(60)
def test_sigkill_mid_run_loses_at_most_the_last_interval(tmp_path: Path) -> None:
    # The child reports (count, its own monotonic clock). Every step written more than
    # 2 x interval before the child's last report must survive the kill.
    interval = 0.5
    path = tmp_path / "run.mcap"
    child = start_child(path, "continuous", interval=interval)
    reports: list[tuple[int, float]] = []
    try:
        while True:
            count, t = read_line(child).split()
            reports.append((int(count), float(t)))
            if reports[-1][1] - reports[0][1] >= 3 * interval + 0.5:
                break
    finally:
        kill(child)
    last_t = reports[-1][1]
    must_survive = max(c for c, t in reports if t <= last_t - 2 * interval)
    steps = recovered_steps(path, tmp_path)
    assert len(steps) >= must_survive > 0
