"""Validation of user input at construction time.

Every check names the offending field in its ``ValueError``. Checks are skipped for traced values
(inside ``jit``/``grad``), where the value is unknown; they run when the user builds an object from
concrete numbers, which is where bad input comes from.
"""

from __future__ import annotations

import jax
import numpy as np


def is_concrete(value) -> bool:
    """True unless ``value`` is (or contains) a JAX tracer."""
    return not any(isinstance(leaf, jax.core.Tracer) for leaf in jax.tree_util.tree_leaves(value))


def _as_float(name: str, value) -> float | None:
    if not is_concrete(value):
        return None
    # np.asarray would read None as nan and "0" as 0.0: a number must be given as one.
    if value is None or isinstance(value, (str, bytes, bool)):
        raise ValueError(f"field '{name}' must be a number, got {value!r}")
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"field '{name}' must be a number, got {value!r}") from None
    if arr.ndim != 0:
        raise ValueError(f"field '{name}' must be a scalar, got shape {arr.shape}")
    return float(arr)


def check_finite(name: str, value) -> None:
    v = _as_float(name, value)
    if v is not None and not np.isfinite(v):
        raise ValueError(f"field '{name}' must be finite, got {v}")


def check_positive(name: str, value) -> None:
    """``value`` must be a finite number > 0."""
    v = _as_float(name, value)
    if v is not None and not (np.isfinite(v) and v > 0.0):
        raise ValueError(f"field '{name}' must be a finite number > 0, got {v}")


def check_nonnegative(name: str, value) -> None:
    v = _as_float(name, value)
    if v is not None and not (np.isfinite(v) and v >= 0.0):
        raise ValueError(f"field '{name}' must be a finite number >= 0, got {v}")


def check_int(name: str, value, minimum: int = 1, maximum: int = 2**31 - 1, optional: bool = False) -> int | None:
    """``value`` must be a Python or NumPy integer (not a bool, not a float) in [minimum, maximum]."""
    if optional and value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or not minimum <= value <= maximum:
        bound = f"in [{minimum}, {maximum}]" if maximum < 2**31 - 1 else f">= {minimum}"
        raise ValueError(f"field '{name}' must be an integer {bound}{' or None' if optional else ''}, "
                         f"got {value!r}")
    return int(value)


def check_finite_array(name: str, value) -> None:
    if is_concrete(value) and not np.all(np.isfinite(np.asarray(value))):
        raise ValueError(f"field '{name}' contains non-finite values")
