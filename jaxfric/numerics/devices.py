"""The devices one run's work is split over: a setting read when a program is traced.

Under :func:`run_devices` with two or more devices, a run's element loops give each device an equal share
of the elements (:func:`jaxfric.fem.assembly.internal_force_and_tangent`). Everything else in the program is
replicated: every device runs the same Newton loop on the same values. On a CPU whose cores XLA shows as
host devices (``--xla_force_host_platform_device_count``, which ``jaxfric run`` asks for:
:func:`jaxfric.io.xla_flags.use_host_cores`) the element loop, which one device runs on one core, then runs
on two. The results are the one-device run's to round-off (``tests/test_host_devices.py``). A model
whose contact calls the host (Lemke's pivoting) is not split (:func:`jaxfric.loadpath.run.split_over`).
"""

from __future__ import annotations

import contextlib
import contextvars

__all__ = ["run_devices", "traced_run_devices"]

_DEVICES: contextvars.ContextVar[tuple | None] = contextvars.ContextVar("run_devices", default=None)


@contextlib.contextmanager
def run_devices(devices):
    """Trace the programs made in this block with one run's work split over ``devices`` (a sequence of two or
    more devices; None or one device: not split). A program already compiled keeps its setting;
    :func:`jaxfric.loadpath.run.run` keys its compiled programs by it."""
    devices = None if devices is None or len(devices) < 2 else tuple(devices)
    token = _DEVICES.set(devices)
    try:
        yield
    finally:
        _DEVICES.reset(token)


def traced_run_devices() -> tuple | None:
    """The :func:`run_devices` setting in effect: a tuple of two or more devices, or None."""
    return _DEVICES.get()
