"""The grid's progress display (capevo.experiment.progress): counts of cells done, running and
failed, in the live bar and in the plain lines of a non-terminal run; it never raises (invariant 1)
and closes once (invariant 2)."""

from __future__ import annotations

import io

from rich.console import Console

from capevo.experiment.progress import GridProgress, RecordingGridProgress, RichGridProgress


def _drive(p: GridProgress) -> None:
    p.started(total=4, done=1, failed=0)
    p.update(running=2)
    p.cell_finished("T1-s-ecm-s1", ok=True, summary="2 iterations")
    p.cell_finished("T6-am-s1", ok=False, summary="Invalid: boom")
    p.message("retrying")
    p.close()
    p.close()


def test_plain_lines_count_cells_done_failed_and_left() -> None:
    out = io.StringIO()
    p = RichGridProgress(Console(file=out, force_terminal=False, width=200), live=False)
    _drive(p)
    text = out.getvalue()
    assert "experiment: 4 cells, 1 done and 0 failed already" in text
    assert "[2 done, 0 failed, 2 left] done T1-s-ecm-s1: 2 iterations" in text
    assert "[2 done, 1 failed, 1 left] FAILED T6-am-s1: Invalid: boom" in text
    assert "retrying" in text


def test_the_live_bar_shows_done_running_failed_and_an_eta() -> None:
    out = io.StringIO()
    p = RichGridProgress(Console(file=out, force_terminal=True, width=200), live=True)
    _drive(p)
    text = out.getvalue()
    assert "done 2 · running 2 · failed 1" in text and "ETA" in text
    assert "3/4" in text


def test_a_broken_console_never_reaches_the_runner() -> None:
    class Broken:
        is_terminal = False

        def print(self, *args: object, **kwargs: object) -> None:
            raise OSError("stderr closed")

    _drive(RichGridProgress(Broken(), live=False))


def test_the_recording_sink_keeps_every_call() -> None:
    p = RecordingGridProgress()
    _drive(p)
    assert [c for c, _ in p.calls] == [
        "started",
        "update",
        "cell_finished",
        "cell_finished",
        "message",
        "close",
        "close",
    ]
    assert isinstance(p, GridProgress) and isinstance(RichGridProgress(live=False), GridProgress)
