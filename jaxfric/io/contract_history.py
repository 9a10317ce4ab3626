"""The run-directory checker (:mod:`jaxfric.io.contract`), section 2: ``history.csv``."""

from __future__ import annotations

import math
import os

from .contract_spec import (
    ATOL,
    INT_EXTRAS,
    INT_REQUIRED,
    NAME,
    REQUIRED,
    STEADY_TOL,
    TIME_TOL,
)

__all__ = ["read_history", "steady"]

# ---- 2. history.csv -------------------------------------------------------------------------------

def read_history(path: str, scene: dict | None, out: list) -> dict | None:
    """Parse and check history.csv; returns the columns (ints, floats or strings) or None."""
    p = os.path.join(path, "history.csv")
    if not os.path.isfile(p) or os.path.getsize(p) == 0:
        return None
    try:
        with open(p, "rb") as f:
            text = f.read().decode("utf-8")
    except UnicodeDecodeError:
        out.append("history.csv: not UTF-8")
        return None
    if "\r" in text:
        out.append("history.csv: line ends must be \\n")
    if '"' in text:
        out.append("history.csv: quoting is not allowed")
    lines = text.split("\n")
    if lines and lines[-1] == "":
        lines = lines[:-1]
    if not lines:
        out.append("history.csv: no header")
        return None
    header = lines[0].split(",")
    if tuple(header[:12]) != REQUIRED:
        out.append(f"history.csv: first 12 columns must be {','.join(REQUIRED)}; got {','.join(header[:12])}")
        return None
    extras = header[12:]
    if len(set(header)) != len(header):
        out.append("history.csv: repeated column names")
    for name in extras:
        if not NAME.match(name):
            out.append(f"history.csv: invalid extra column name {name!r}")
    rows = [line.split(",") for line in lines[1:]]
    if not rows:
        out.append("history.csv: no data rows")
        return None
    for i, row in enumerate(rows):
        if len(row) != len(header):
            out.append(f"history.csv: row {i} has {len(row)} fields, header has {len(header)}")
            return None
        if any(field == "" for field in row):
            out.append(f"history.csv: row {i} has an empty field")
            return None
    cols: dict[str, list] = {}  # column name -> its str, int or float values, by column
    for k, name in enumerate(header):
        raw = [row[k] for row in rows]
        if name == "phase":
            cols[name] = raw
            continue
        if name in INT_REQUIRED or name in INT_EXTRAS:
            try:
                cols[name] = [int(v) for v in raw]
            except ValueError:
                out.append(f"history.csv: column {name!r} must hold integers")
                return None
            continue
        try:
            values = [float(v) for v in raw]
        except ValueError:
            if name in REQUIRED:
                out.append(f"history.csv: column {name!r} must be numeric")
                return None
            continue  # a non-numeric extra column
        if not all(math.isfinite(v) for v in values):
            out.append(f"history.csv: column {name!r} has non-finite values")
        cols[name] = values
    n = len(rows)
    if cols["step"] != list(range(n)):
        out.append("history.csv: 'step' must equal the row index 0, 1, 2, ...")
    time = cols["time"]
    if time[0] != 0.0:
        out.append("history.csv: 'time' must start at 0")
    if any(b < a for a, b in zip(time, time[1:])):
        out.append("history.csv: 'time' decreases")
    if cols["newton_iters"][0] != 0:
        out.append("history.csv: 'newton_iters' must be 0 on row 0")
    for name in ("drawing_force", "clamping_force", "wall_s"):
        if abs(cols[name][0]) > ATOL:
            out.append(f"history.csv: '{name}' must be 0 on row 0 (initial state)")
    if any(v < 0 for v in cols["max_penetration"]):
        out.append("history.csv: 'max_penetration' < 0")
    if any(s < 0 or s > a for a, s in zip(cols["n_active"], cols["n_slip"])):
        out.append("history.csv: 0 <= n_slip <= n_active violated")
    if any(v < 0 for v in cols["newton_iters"]):
        out.append("history.csv: 'newton_iters' < 0")
    if any(v < 0 for v in cols["wall_s"]):
        out.append("history.csv: 'wall_s' < 0")
    for name in INT_EXTRAS:
        if name in cols and any(v < 0 for v in cols[name]):
            out.append(f"history.csv: '{name}' < 0")
    if scene is not None:
        phases = scene["phases"]
        unknown = sorted(set(cols["phase"]) - set(phases))
        if unknown:
            out.append(f"history.csv: phases {unknown} not in the scene vocabulary {list(phases)}")
        else:
            index = [phases.index(p) for p in cols["phase"]]
            if index[0] != 0:
                out.append(f"history.csv: row 0 phase must be {phases[0]!r}")
            if any(b < a for a, b in zip(index, index[1:])):
                out.append("history.csv: phase index decreases")
            if not all(-TIME_TOL <= t <= len(phases) + TIME_TOL for t in time):
                out.append(f"history.csv: 'time' outside [0, {len(phases)}]")
            if not all(k - TIME_TOL <= t <= k + 1 + TIME_TOL for k, t in zip(index, time)):
                out.append("history.csv: 'time' of a row outside its phase interval [k-1, k]")
            u = cols["drawing_displacement"]
            draw = [i for i, p in enumerate(cols["phase"]) if p == "draw"]
            first = draw[0] if draw else n
            if any(u[i] != 0.0 for i in range(first)):
                out.append("history.csv: 'drawing_displacement' must be 0 before the first draw row")
            if any(u[b] < u[a] for a, b in zip(draw, draw[1:])):
                out.append("history.csv: 'drawing_displacement' decreases on draw rows")
    return cols


def steady(cols: dict, window) -> float | None:
    """Steady drawing force (benchmarks spec section 6), recomputed from the history."""
    a, b = window
    idx = [i for i, p in enumerate(cols["phase"])
           if p == "draw" and a - STEADY_TOL <= cols["drawing_displacement"][i] <= b + STEADY_TOL]
    if len(idx) < 2:
        return None
    u = [cols["drawing_displacement"][i] for i in idx]
    f = [cols["drawing_force"][i] for i in idx]
    span = u[-1] - u[0]
    if span <= 0 or span < 0.5 * (b - a):
        return None
    return sum(0.5 * (f[k] + f[k + 1]) * (u[k + 1] - u[k]) for k in range(len(u) - 1)) / span
