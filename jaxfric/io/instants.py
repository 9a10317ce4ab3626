"""What a run's history says at named points: its named instants and its steady drawing force
(benchmarks spec, scene Outputs and section 6; outputs spec section 4). Each scene module declares its
phases and its instants' rules; these functions read any history, a run's or a measured one."""

from __future__ import annotations

import numpy as np

from .. import scenes

__all__ = ["STEADY_TOL", "TIME_TOL", "select_instants", "InstantRows", "instant_rows", "steady_rows",
           "steady_drawing_force", "steady_window", "phase_names", "column", "scene_module"]

STEADY_TOL = 1e-9        # mm; inclusive window tolerance (benchmarks spec section 6)
TIME_TOL = 1e-9         # pseudo-time tolerance for "end of phase k" (time = k)


# Instant rules (each scene module's INSTANT_RULES; benchmarks spec, scene Outputs). Each rule is one of
#   ("end", phase)              : the row where `phase` ends (time = its index); omitted if never reached
#   ("closest", phase, value)   : the `phase` row with drawing_displacement closest to value (mm)
#   ("first_half_slip",)        : first draw row with n_active > 0 and n_slip >= n_active / 2
#   ("first_all_slip",)         : first draw row with n_active > 0 and n_slip == n_active
#   ("final",)                  : the last row


def scene_module(name: str):
    """The scene module of ``name`` (its PHASES and INSTANT_RULES), or None for an unknown name."""
    return scenes.SCENES.get(name)


# ---- history access ---------------------------------------------------------------------------------

def phase_names(scene_name: str, history: dict) -> np.ndarray:
    """Phase name of every history row, from ``phase_name`` or from ``phase`` (names or indices)."""
    if "phase_name" in history:
        return np.asarray(history["phase_name"]).astype(str)
    phase = np.asarray(history["phase"])
    if phase.dtype.kind in "US":
        return phase.astype(str)
    vocabulary = scene_module(scene_name).PHASES
    return np.array([vocabulary[int(k)] for k in phase])


def column(history: dict, name: str) -> np.ndarray:
    if name not in history:
        raise KeyError(f"history has no column {name!r} (the scene's observe must provide it)")
    return np.asarray(history[name])


# ---- named instants ---------------------------------------------------------------------------------

def select_instants(scene_name: str, history: dict) -> tuple[list, list, list]:
    """Named instants of a run (benchmarks spec, scene Outputs; outputs spec section 4).

    Args:
        scene_name: ``flat_die``, ``bead``, ``nine`` or ``blankholder``.
        history: per-row arrays with ``time``, ``phase_name`` (or ``phase``: names or indices),
            ``drawing_displacement`` (mm), ``n_active`` and ``n_slip``; row 0 is the initial state.

    Returns:
        ``(names, rows, fallback)``: instant names in scene order, their history rows (= ``step``), and
        the state-based instants that never occurred and were put on the last row. An instant whose
        phase was never reached (``end`` of a phase that was not completed, ``closest`` in a phase that
        has no row) is omitted; ``final`` (the last row) is always present.
    """
    module = scene_module(scene_name)
    if module is None:
        raise ValueError(f"unknown scene {scene_name!r}; choose one of {', '.join(scenes.scene_names())}")
    phases = phase_names(scene_name, history)
    time = np.asarray(history["time"], dtype=np.float64)
    last = len(time) - 1
    vocabulary = module.PHASES
    names, rows, fallback = [], [], []
    for name, rule in module.INSTANT_RULES.items():
        kind = rule[0]
        row = None
        if kind == "final":
            row = last
        elif kind == "end":  # phase k (1-based) ends at time k
            k = vocabulary.index(rule[1]) + 1
            hits = np.flatnonzero((phases == rule[1]) & (np.abs(time - k) <= TIME_TOL))
            row = int(hits[-1]) if hits.size else None
        elif kind == "closest":
            in_phase = np.flatnonzero(phases == rule[1])
            if in_phase.size:
                u = np.asarray(history["drawing_displacement"], dtype=np.float64)[in_phase]
                row = int(in_phase[np.argmin(np.abs(u - rule[2]))])  # first of equals
        else:  # state-based, in the draw phase
            draw = np.flatnonzero(phases == "draw")
            if draw.size:
                active = np.asarray(history["n_active"])[draw]
                slip = np.asarray(history["n_slip"])[draw]
                if kind == "first_half_slip":
                    ok = (active > 0) & (2 * slip >= active)
                else:
                    ok = (active > 0) & (slip == active)
                hits = draw[ok]
                if hits.size:
                    row = int(hits[0])
                else:
                    row = last
                    fallback.append(name)
        if row is not None:
            names.append(name)
            rows.append(row)
    return names, rows, fallback


def _as_written(values) -> np.ndarray:
    """``values`` as ``history.csv`` writes and reads them back (``%.12g``)."""
    return np.array([float(f"{float(v):.12g}") for v in np.asarray(values)])


class InstantRows:
    """The rows whose state ``contact.npz`` can still need, given a run's rows so far (a run's
    ``keep_snapshots``): the instants that :func:`select_instants` picks from them as ``history.csv``
    writes them, and the last row.

    A later row can replace an instant's row (a closer displacement, a first slip, the final row) but
    never bring back an older row that no rule picks now: "end" rows are fixed once reached, "closest"
    keeps the first of equals, the state-based rules take the first hit. So a run may drop the
    snapshots of every other row as it goes.

    Called after every chunk with the whole history, it rounds only the rows it has not seen (the
    rounding through text is what costs; a run's recorded rows never change), so a long run's calls cost
    O(rows) in all, not O(rows^2); a history whose earlier rows differ from those seen starts over.
    """

    _COLUMNS = ("time", "drawing_displacement")

    def __init__(self, scene_name: str):
        self.scene_name = scene_name
        self._seen = {name: (np.empty(0), np.empty(0)) for name in self._COLUMNS}  # raw, as written

    def _written(self, history: dict, name: str) -> np.ndarray:
        values = np.asarray(column(history, name), dtype=np.float64)
        raw, written = self._seen[name]
        n = raw.size
        if values.size < n or not np.array_equal(values[:n], raw):
            raw, written, n = np.empty(0), np.empty(0), 0
        written = np.concatenate([written, _as_written(values[n:])])
        self._seen[name] = (values, written)
        return written

    def __call__(self, history: dict) -> list:
        h = dict(history)
        for name in self._COLUMNS:
            h[name] = self._written(history, name)
        _, rows, _ = select_instants(self.scene_name, h)
        return sorted(set(rows) | {len(h["time"]) - 1})


def instant_rows(scene_name: str, history: dict) -> list:
    """:class:`InstantRows` of one history."""
    return InstantRows(scene_name)(history)


# ---- steady drawing force ---------------------------------------------------------------------------

def steady_rows(phases, displacement, window) -> np.ndarray:
    """Indices of the ``draw`` rows whose drawing displacement lies in ``window`` (inclusive, mm,
    tolerance 1e-9 mm), in step order (benchmarks spec section 6)."""
    a, b = float(window[0]), float(window[1])
    u = np.asarray(displacement, dtype=np.float64)
    mask = (np.asarray(phases).astype(str) == "draw") & (u >= a - STEADY_TOL) & (u <= b + STEADY_TOL)
    return np.flatnonzero(mask)


def steady_drawing_force(history: dict, window) -> float | None:
    """Steady drawing force F̄ (N/mm) over ``window`` = (a, b) in drawing displacement (mm).

    F̄ = trapz(drawing_force, drawing_displacement) / (U_last - U_first) over the ``draw`` rows in the
    window (benchmarks spec section 6). Returns None if fewer than 2 rows qualify or if
    U_last - U_first < (b - a) / 2.

    Args:
        history: per-row arrays ``phase_name`` (or ``phase`` as names), ``drawing_displacement`` (mm),
            ``drawing_force`` (N/mm).
    """
    phases = history["phase_name"] if "phase_name" in history else history["phase"]
    u = np.asarray(history["drawing_displacement"], dtype=np.float64)
    f = np.asarray(history["drawing_force"], dtype=np.float64)
    rows = steady_rows(phases, u, window)
    if rows.size < 2:
        return None
    u, f = u[rows], f[rows]
    span = float(u[-1] - u[0])
    if span <= 0.0 or span < 0.5 * (float(window[1]) - float(window[0])):
        return None
    area = float(np.sum(0.5 * (f[1:] + f[:-1]) * np.diff(u)))
    return area / span


def steady_window(scene_name: str, history: dict, default) -> tuple[tuple, str]:
    """The steady window actually used, and a note for ``summary.json`` ``message`` ("" if unchanged).

    Nine scene (benchmarks spec section 4): the default window [20, 35] mm is valid if the free end is
    still upstream of shoulder A, ``tail_x`` < -1 mm, up to its end. Otherwise the window ends at the
    last ``draw`` row before ``tail_x`` first reaches -1 mm. Other scenes use ``default``.
    """
    a, b = float(default[0]), float(default[1])
    if scene_name != "nine" or "tail_x" not in history:
        return (a, b), ""
    phases = phase_names(scene_name, history)
    u = np.asarray(history["drawing_displacement"], dtype=np.float64)
    tail = np.asarray(history["tail_x"], dtype=np.float64)
    draw = np.flatnonzero(phases == "draw")
    bad = draw[(tail[draw] >= -1.0) & (u[draw] <= b + STEADY_TOL)]
    if bad.size == 0:
        return (a, b), ""
    before = draw[draw < bad[0]]
    new_b = float(u[before[-1]]) if before.size else a
    new_b = min(max(new_b, a), b)
    note = (f"steady window shortened from [{a:g}, {b:g}] to [{a:g}, {new_b:.6g}] mm: the free end "
            f"reached tail_x = {tail[bad[0]]:.4g} mm >= -1 mm at U = {u[bad[0]]:.6g} mm")
    return (a, new_b), note
