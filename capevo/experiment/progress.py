"""Progress of an experiment grid: cells done, running and failed, with an ETA (issue 20).

The runner reports through the narrow :class:`GridProgress` protocol. :class:`RichGridProgress`
draws one ``rich.progress`` bar on stderr when it is a terminal (a plain line per finished cell
otherwise, so the log of a non-interactive run stays readable); :class:`RecordingGridProgress`
keeps the calls for tests. Like :mod:`capevo.evolve.progress`, whose style it follows.

"Running" is the number of submitted cells Ray may be running (at most the worker slots): Ray
does not tell the driver when a queued task starts. The ETA is rich's, from the rate at which
cells finished in this run (the cells skipped as already done do not count towards it).

Invariants:
1. A sink never raises into the runner (:class:`RichGridProgress` swallows and logs its errors).
2. ``close`` is idempotent.
"""

from __future__ import annotations

import logging
from typing import Any, Protocol, runtime_checkable

from capevo.evolve.progress import RichDisplay

log = logging.getLogger(__name__)


@runtime_checkable
class GridProgress(Protocol):
    """What the runner tells about a grid."""

    def started(self, *, total: int, done: int, failed: int) -> None:
        """The grid has ``total`` cells; ``done`` finished and ``failed`` failed in an earlier run."""
        ...

    def update(self, *, running: int) -> None: ...

    def cell_finished(self, name: str, *, ok: bool, summary: str) -> None: ...

    def message(self, text: str) -> None: ...

    def close(self) -> None: ...


class RecordingGridProgress:
    """In-memory :class:`GridProgress`: every call appended to :attr:`calls` as ``(name, args)``."""

    def __init__(self) -> None:
        self.calls: list[tuple[str, dict[str, Any]]] = []

    def started(self, *, total: int, done: int, failed: int) -> None:
        self.calls.append(("started", {"total": total, "done": done, "failed": failed}))

    def update(self, *, running: int) -> None:
        self.calls.append(("update", {"running": running}))

    def cell_finished(self, name: str, *, ok: bool, summary: str) -> None:
        self.calls.append(("cell_finished", {"name": name, "ok": ok, "summary": summary}))

    def message(self, text: str) -> None:
        self.calls.append(("message", {"text": text}))

    def close(self) -> None:
        self.calls.append(("close", {}))


class RichGridProgress(RichDisplay):
    """One bar of cells with done / running / failed counts and rich's ETA, on stderr.

    Args:
        console: A rich console; default one on stderr.
        live: Draw a live bar; default: only when the console is a terminal.
    """

    def __init__(self, console: Any = None, *, live: bool | None = None) -> None:
        super().__init__(console, live=live)
        self._bar: Any = None
        self.total = self.done = self.failed = self.running = 0

    def _fields(self) -> dict[str, Any]:
        return {"done": self.done, "running": self.running, "failed": self.failed}

    def started(self, *, total: int, done: int, failed: int) -> None:
        def go() -> None:
            self.total, self.done, self.failed = total, done, failed
            if self.live:
                from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

                self._progress = Progress(
                    TextColumn("cells"),
                    BarColumn(),
                    MofNCompleteColumn(),
                    TextColumn(
                        "done {task.fields[done]} · running {task.fields[running]} · failed {task.fields[failed]}"
                    ),
                    TextColumn("ETA"),
                    TimeRemainingColumn(),
                    console=self.console,
                )
                self._progress.start()
                self._bar = self._progress.add_task("cells", total=total, completed=done + failed, **self._fields())
            else:
                self.console.print(f"experiment: {total} cells, {done} done and {failed} failed already", markup=False)

        self._guard(go)

    def update(self, *, running: int) -> None:
        def go() -> None:
            self.running = running
            if self._progress is not None:
                self._progress.update(self._bar, **self._fields())

        self._guard(go)

    def cell_finished(self, name: str, *, ok: bool, summary: str) -> None:
        def go() -> None:
            if ok:
                self.done += 1
            else:
                self.failed += 1
            line = f"{'done' if ok else 'FAILED'} {name}: {summary}"
            if self._progress is not None:
                self._progress.update(self._bar, advance=1, **self._fields())
                self._progress.console.print(line, markup=False)
            else:
                left = self.total - self.done - self.failed
                self.console.print(f"[{self.done} done, {self.failed} failed, {left} left] {line}", markup=False)

        self._guard(go)


__all__ = ["GridProgress", "RecordingGridProgress", "RichGridProgress"]
