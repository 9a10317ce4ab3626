"""A text progress bar for load paths that return to the host between chunks of steps.

:func:`jaxfric.loadpath.run.run` calls :meth:`ProgressMonitor.update` after every chunk (about once a
second); the compiled program itself never calls the host.
"""

from __future__ import annotations

import sys
import time

__all__ = ["ProgressMonitor"]


class ProgressMonitor:
    """Draws a bar on ``stream`` when ``show``: redrawn in place on a terminal (at most every
    ``min_interval`` s); in a log file one line per tenth of the load path, and one after ``log_interval``
    s without a line (a run whose steps have shrunk still shows its step count moving). Use as a context
    manager."""

    def __init__(self, total_time: float, show: bool = True, stream=None, label: str = "",
                 min_interval: float = 0.1, log_interval: float = 60.0):
        self.total_time = float(total_time)
        self.show = show
        self.stream = sys.stderr if stream is None else stream
        self.label = label
        self.min_interval = min_interval
        self.log_interval = log_interval
        self.start = time.perf_counter()
        self._drawn = False
        self._last_draw = self.start
        self._last_tenth = 0
        self._tty = bool(getattr(self.stream, "isatty", lambda: False)())

    def __enter__(self):
        self.start = self._last_draw = time.perf_counter()
        return self

    def __exit__(self, *exc):
        if self.show and self._drawn and self._tty:
            self.stream.write("\n")
            self.stream.flush()
        return False

    def update(self, step: int, t: float, iterations: int, cuts: int) -> None:
        """The load path stands at history row ``step``, pseudo-time ``t``; ``iterations`` and ``cuts``:
        the Newton iterations and cut attempts of its last step."""
        if not self.show:
            return
        now = time.perf_counter()
        frac = min(max(t / self.total_time, 0.0), 1.0)
        if self._tty:  # redraw in place, at most every min_interval
            if now - self._last_draw < self.min_interval and frac < 1.0:
                return
            start, end = "\r", ""
        else:  # a log file: one line per tenth of the load path, or after log_interval without one
            if int(10 * frac) <= self._last_tenth and now - self._last_draw < self.log_interval:
                return
            self._last_tenth = max(self._last_tenth, int(10 * frac))
            start, end = "", "\n"
        self._last_draw = now
        self._drawn = True
        bar = "#" * int(30 * frac) + "." * (30 - int(30 * frac))
        self.stream.write(f"{start}{self.label}[{bar}] t={t:.4f}/{self.total_time:g} step {step} "
                          f"newton {iterations} cuts {cuts} {now - self.start:7.1f}s{end}")
        self.stream.flush()

    def note(self, text: str) -> None:
        """A line of its own about the run (an event between chunks), under the bar when ``show``."""
        if not self.show:
            return
        self.stream.write(f"{chr(10) if self._tty and self._drawn else ''}{self.label}{text}\n")
        self.stream.flush()
        self._drawn = False
