"""Progress bars for the command line (rich, on stderr, only when stderr is a terminal).

Library functions that take long accept an optional ``progress`` callback and call it as
``progress(what, done, total)`` (``what``: the phase, e.g. ``"candidate effects"``, or
``"phase: detail"`` to say what runs now; ``done`` of ``total`` units finished; ``total`` may
grow as the work turns out larger).
They never draw anything themselves.  :func:`progress_bar` gives the command line such a
callback, drawing one bar per phase; :meth:`Bar.step` marks the command's own phases
(reading, least squares, drawing, ...).  When stderr is not a terminal (a pipe, a log
file, a test) the callback does nothing, so output stays as it was.
"""

from __future__ import annotations

import sys
from collections.abc import Iterator
from contextlib import contextmanager


class Bar:
    """The ``progress(what, done, total)`` callback of a command, and its own phases (:meth:`step`)."""

    def __init__(self, live=None, phases: int | None = None):
        self._live = live
        self._tasks: dict[str, int] = {}
        self._phases = phases
        self._phase_task = None
        self._done = 0

    @property
    def enabled(self) -> bool:
        return self._live is not None

    def __call__(self, what: str, done: int, total: int | None) -> None:
        """One bar per phase; ``"phase: detail"`` updates the bar ``phase`` and shows the detail."""
        if self._live is None:
            return
        key = what.split(": ", 1)[0]
        task = self._tasks.get(key)
        if task is None:
            task = self._tasks[key] = self._live.add_task(what, total=total)
        self._live.update(task, completed=done, total=total, description=what)

    def step(self, what: str) -> None:
        """The command starts its next phase ``what`` (e.g. "least squares", "drawing")."""
        if self._live is None:
            return
        if self._phase_task is None:
            self._phase_task = self._live.add_task(what, total=self._phases)
        else:
            self._done += 1
            self._live.update(self._phase_task, completed=self._done, description=what)

    def iterate(self, items, what: str):
        """``items`` one by one, advancing the bar ``what`` after each."""
        items = list(items)
        self(what, 0, len(items))
        for j, item in enumerate(items, 1):
            yield item
            self(what, j, len(items))


@contextmanager
def progress_bar(phases: int | None = None, *, enabled: bool | None = None) -> Iterator[Bar]:
    """A :class:`Bar` drawing on stderr while the block runs (removed at the end); a silent one unless stderr is a
    terminal (``enabled`` overrides).  ``phases``: how many :meth:`Bar.step` calls the command makes."""
    if enabled is None:
        enabled = sys.stderr.isatty()
    if not enabled:
        yield Bar()
        return
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    from ambfit.faces.cli.app import err

    with Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                  console=err, transient=True) as live:
        yield Bar(live, phases)
