"""A text progress bar fed from inside jitted load loops with ``jax.debug.callback``.

The jitted loop calls :func:`report` at the end of every accepted step; ``report`` forwards to the
monitor that the public entry point activated (host side), which draws the bar and keeps a time stamp
per step so that wall time per step can be written without leaving JAX.
"""

from __future__ import annotations

import sys
import time

import numpy as np

__all__ = ["ProgressMonitor", "report", "active"]

_ACTIVE: ProgressMonitor | None = None


class ProgressMonitor:
    """Receives step reports; draws a bar on ``stream`` when ``show`` and stores time stamps.

    Use as a context manager around the call of a jitted simulation.
    """

    def __init__(self, total_time: float, show: bool = True, stream=None, label: str = "",
                 min_interval: float = 0.1):
        self.total_time = float(total_time)
        self.show = show
        self.stream = sys.stderr if stream is None else stream
        self.label = label
        self.min_interval = min_interval
        self.stamps: dict[int, float] = {}
        self.snapshots: dict[int, object] = {}
        self.start = None
        self._last_draw = 0.0
        self._last_tenth = 0
        self._tty = bool(getattr(self.stream, "isatty", lambda: False)())

    def __enter__(self):
        global _ACTIVE
        self._previous = _ACTIVE
        _ACTIVE = self
        self.start = time.perf_counter()
        return self

    def __exit__(self, *exc):
        global _ACTIVE
        _ACTIVE = self._previous
        if self.show and self.stamps and self._tty:
            self.stream.write("\n")
            self.stream.flush()
        return False

    def on_step(self, step, t, iterations, cuts, snapshot=None):
        now = time.perf_counter()
        step, t = np.asarray(step), np.asarray(t)
        # Under vmap the arguments are batched: report the slowest member.
        self.stamps[int(np.min(step))] = now
        if snapshot is not None and step.ndim == 0:
            self.snapshots[int(step)] = snapshot
        if not self.show:
            return
        frac = float(np.clip(np.min(t) / self.total_time, 0.0, 1.0))
        if self._tty:  # redraw in place, at most every min_interval
            if now - self._last_draw < self.min_interval and frac < 1.0:
                return
            start, end = "\r", ""
        else:  # a log file: one line per tenth of the load path
            if int(10 * frac) <= self._last_tenth:
                return
            self._last_tenth = int(10 * frac)
            start, end = "", "\n"
        self._last_draw = now
        bar = "#" * int(30 * frac) + "." * (30 - int(30 * frac))
        self.stream.write(
            f"{start}{self.label}[{bar}] t={float(np.min(t)):.4f}/{self.total_time:g} "
            f"step {int(np.min(step))} newton {int(np.max(iterations))} cuts {int(np.max(cuts))} "
            f"{now - self.start:7.1f}s{end}")
        self.stream.flush()

    def step_wall_times(self, n_rows: int) -> np.ndarray:
        """Wall time (s) of steps 0..n_rows-1 from the time stamps (row 0: 0)."""
        out = np.zeros(n_rows)
        previous = self.start
        for k in range(1, n_rows):
            stamp = self.stamps.get(k)
            if stamp is not None and previous is not None:
                out[k] = max(stamp - previous, 0.0)
                previous = stamp
        return out


def active() -> ProgressMonitor | None:
    return _ACTIVE


def report(step, t, iterations, cuts, snapshot=None):
    """Host side of the in-loop callback; ``snapshot`` (a pytree of arrays, optional) is kept per step."""
    if _ACTIVE is not None:
        _ACTIVE.on_step(step, t, iterations, cuts, snapshot)
