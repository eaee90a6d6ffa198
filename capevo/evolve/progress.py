"""Progress of an evolution run: iterations, episodes and learner steps.

The loop reports through the narrow :class:`ProgressSink` protocol. :class:`RichProgress`
draws three ``rich.progress`` bars on stderr when it is a terminal (and prints one plain line
per phase and per iteration otherwise, so logs of a non-interactive run stay readable);
:class:`RecordingProgress` keeps the calls in memory for tests.

Invariants:
1. A sink never raises into the loop: :class:`RichProgress` swallows and logs its own errors.
2. ``close`` is idempotent and stops the live display.
"""

from __future__ import annotations

import logging
from typing import Any, Protocol, runtime_checkable

log = logging.getLogger(__name__)


@runtime_checkable
class ProgressSink(Protocol):
    """What the loop tells about its progress."""

    def run_started(self, *, task: str, total: int, completed: int) -> None: ...

    def iteration_started(self, iteration: int) -> None: ...

    def phase(self, name: str, *, episodes: int) -> None:
        """A phase (``live``, ``monitor``, ``learn``, ``gate``, ``final``) begins with ``episodes`` episodes planned."""
        ...

    def episodes_done(self, n: int = 1) -> None: ...

    def learner_started(self, *, total: int, unit: str) -> None: ...

    def learner_advance(self, n: int = 1) -> None: ...

    def iteration_finished(self, iteration: int, summary: str) -> None: ...

    def message(self, text: str) -> None: ...

    def close(self) -> None: ...


class RecordingProgress:
    """In-memory :class:`ProgressSink`: every call appended to :attr:`calls` as ``(name, args)``."""

    def __init__(self) -> None:
        self.calls: list[tuple[str, dict[str, Any]]] = []

    def _add(self, call: str, **kw: Any) -> None:
        self.calls.append((call, kw))

    def run_started(self, *, task: str, total: int, completed: int) -> None:
        self._add("run_started", task=task, total=total, completed=completed)

    def iteration_started(self, iteration: int) -> None:
        self._add("iteration_started", iteration=iteration)

    def phase(self, name: str, *, episodes: int) -> None:
        self._add("phase", name=name, episodes=episodes)

    def episodes_done(self, n: int = 1) -> None:
        self._add("episodes_done", n=n)

    def learner_started(self, *, total: int, unit: str) -> None:
        self._add("learner_started", total=total, unit=unit)

    def learner_advance(self, n: int = 1) -> None:
        self._add("learner_advance", n=n)

    def iteration_finished(self, iteration: int, summary: str) -> None:
        self._add("iteration_finished", iteration=iteration, summary=summary)

    def message(self, text: str) -> None:
        self._add("message", text=text)

    def close(self) -> None:
        self._add("close")

    def names(self) -> list[str]:
        return [c[0] for c in self.calls]


class RichDisplay:
    """What a rich progress display on stderr shares (the loop's and the experiment grid's): its
    console, whether it draws live bars, a guard that keeps a display failure from stopping the
    work, printed messages and closing.

    Args:
        console: A rich console; default one on stderr.
        live: Draw live bars; default: only when the console is a terminal. Without them every
            event is one printed line.
    """

    def __init__(self, console: Any = None, *, live: bool | None = None) -> None:
        from rich.console import Console

        self.console = console if console is not None else Console(stderr=True, highlight=False)
        self.live = self.console.is_terminal if live is None else live
        self._progress: Any = None
        self._closed = False

    def _guard(self, fn: Any, *args: Any, **kw: Any) -> None:
        try:
            fn(*args, **kw)
        except Exception:  # the display must never stop the work
            log.exception("progress display failed")

    def message(self, text: str) -> None:
        def go() -> None:
            console = self._progress.console if self._progress is not None else self.console
            console.print(text, markup=False)

        self._guard(go)

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        if self._progress is not None:
            self._guard(self._progress.stop)


class RichProgress(RichDisplay):
    """Three bars (iterations, episodes of the current phase, learner steps) on stderr.

    Args:
        console: A rich console; default one on stderr.
        live: Draw live bars; default: only when the console is a terminal. Without them every
            phase and iteration is one printed line.
    """

    def __init__(self, console: Any = None, *, live: bool | None = None) -> None:
        super().__init__(console, live=live)
        self._iter: Any = None
        self._eps: Any = None
        self._learn: Any = None
        self._phase = ""
        self._task = ""

    def run_started(self, *, task: str, total: int, completed: int) -> None:
        def go() -> None:
            self._task = task
            if self.live:
                from rich.progress import (
                    BarColumn,
                    MofNCompleteColumn,
                    Progress,
                    TextColumn,
                    TimeElapsedColumn,
                )

                self._progress = Progress(
                    TextColumn("{task.description:<28}"),
                    BarColumn(),
                    MofNCompleteColumn(),
                    TimeElapsedColumn(),
                    console=self.console,
                    transient=False,
                )
                self._progress.start()
                self._iter = self._progress.add_task(f"{task}: iterations", total=total, completed=completed)
                self._eps = self._progress.add_task("episodes", total=1, completed=0)
                self._learn = self._progress.add_task("learner", total=1, completed=0)
            else:
                self.console.print(f"evolve {task}: {completed}/{total} iterations done", markup=False)

        self._guard(go)

    def iteration_started(self, iteration: int) -> None:
        def go() -> None:
            if self._progress is not None:
                self._progress.update(self._iter, description=f"{self._task}: iteration {iteration}")
            else:
                self.console.print(f"iteration {iteration}: started", markup=False)

        self._guard(go)

    def phase(self, name: str, *, episodes: int) -> None:
        def go() -> None:
            self._phase = name
            if self._progress is not None:
                self._progress.reset(self._eps, total=max(episodes, 1), completed=0, description=f"episodes ({name})")
            else:
                self.console.print(f"  {name}: {episodes} episodes", markup=False)

        self._guard(go)

    def episodes_done(self, n: int = 1) -> None:
        if self._progress is not None:
            self._guard(self._progress.advance, self._eps, n)

    def learner_started(self, *, total: int, unit: str) -> None:
        def go() -> None:
            if self._progress is not None:
                self._progress.reset(self._learn, total=max(total, 1), completed=0, description=f"learner ({unit})")
            else:
                self.console.print(f"  learner: {total} {unit}", markup=False)

        self._guard(go)

    def learner_advance(self, n: int = 1) -> None:
        if self._progress is not None:
            self._guard(self._progress.advance, self._learn, n)

    def iteration_finished(self, iteration: int, summary: str) -> None:
        def go() -> None:
            if self._progress is not None:
                self._progress.advance(self._iter, 1)
                self._progress.console.print(f"iteration {iteration}: {summary}", markup=False)
            else:
                self.console.print(f"iteration {iteration}: {summary}", markup=False)

        self._guard(go)


__all__ = ["ProgressSink", "RecordingProgress", "RichDisplay", "RichProgress"]
