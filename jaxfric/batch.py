"""Running many cases into run directories, resumably (the studies and the accuracy-cost report).

A case is an ordinary :func:`jaxfric.run.run` written by :func:`jaxfric.output.write_run` into its own
directory. A directory that already holds a ``summary.json`` is read back instead of recomputed (unless
``rerun``), so an interrupted study resumes where it stopped, and a case that fails keeps its partial
run directory with the reason in ``summary.json`` ``message``.
"""

from __future__ import annotations

import csv
import json
import math
import os
import time

import numpy as np

__all__ = ["read_history", "phase_curve", "run_case", "stale", "write_csv"]


def read_history(path: str) -> dict:
    """``history.csv`` as a dict of NumPy columns (``phase`` as strings); {} for an empty file."""
    with open(path, newline="") as fh:
        rows = list(csv.DictReader(fh))
    if not rows:
        return {}
    return {k: (np.array([r[k] for r in rows]) if k == "phase" else np.array([float(r[k]) for r in rows]))
            for k in rows[0]}


def phase_curve(history: dict, x_name: str, y_name: str, phase: str):
    """(x, y) of the rows of ``phase``, sorted by x, or None if the phase has fewer than two rows."""
    sel = history["phase"] == phase
    if sel.sum() < 2:
        return None
    x, y = history[x_name][sel], history[y_name][sel]
    order = np.argsort(x, kind="stable")
    return x[order], y[order]


def run_case(out: str, scene_name: str, variant: str | None, algorithm: str, overrides: dict, *,
             rerun: bool = False, progress: bool = False, figures: bool = False, tag: str | None = None,
             log=print) -> dict:
    """Run one case into ``out`` (or read it back) and return ``{"summary", "history", "contact", "dir"}``.

    ``summary`` always has ``converged`` and ``message``: a case that could not even be built or run
    enters with ``converged`` False and the reason (one failed case never stops a batch).
    """
    from . import output, scenes
    from .run import run

    path = os.path.join(out, "summary.json")
    changed = None if rerun or not os.path.exists(path) else stale(path, overrides)
    if changed:
        log(f"{out}: the run on disk has {changed}: rerun")
    if rerun or changed or not os.path.exists(path):
        t0 = time.perf_counter()
        log(f"{out}: {scene_name}/{variant}/{algorithm} {overrides}")
        try:
            scene = scenes.make(scene_name, variant, algorithm, dict(overrides))
            result = run(scene.model, newton=scene.newton, control=scene.control, observe=scene.observe,
                         snapshot=scene.snapshot,
                         progress=progress, raise_on_failure=False, label=f"{os.path.basename(out)} ")
            output.write_run(scene, result, out, tag=tag, figures=figures)
        except output.OutputError as err:  # partial run directory; the reason is in summary.json
            log(f"{out}: {err}")
        except Exception as err:  # noqa: BLE001 - recorded as a failed case
            os.makedirs(out, exist_ok=True)
            message = f"{type(err).__name__}: {err}"
            with open(path, "w") as fh:
                json.dump({"converged": False, "message": message, "scene": scene_name, "variant": variant,
                           "algorithm": algorithm}, fh, indent=2)
            log(f"{out}: failed: {message}")
        log(f"{out}: done in {time.perf_counter() - t0:.1f} s")
    with open(path) as fh:
        summary = json.load(fh)
    hist = os.path.join(out, "history.csv")
    npz = os.path.join(out, "contact.npz")
    return {"summary": summary, "history": read_history(hist) if os.path.exists(hist) else {},
            "contact": dict(np.load(npz, allow_pickle=False)) if os.path.exists(npz) else {}, "dir": out}


def stale(path: str, overrides: dict) -> str | None:
    """How the run recorded in ``path`` (a summary.json) differs from ``overrides`` (``"mesh"`` as
    ``NXxNY``, other keys config fields), or None when it does not (or records no parameters)."""
    with open(path) as fh:
        config = (json.load(fh).get("parameters") or {}).get("config")
    if not config:
        return None
    wanted = dict(overrides)
    if "mesh" in wanted:
        nx, ny = (int(v) for v in str(wanted.pop("mesh")).lower().split("x"))
        wanted.update(nx=nx, ny=ny)
    for key, value in wanted.items():
        if key not in config:
            continue
        have = config[key]
        same = (math.isclose(float(have), float(value), rel_tol=1e-12, abs_tol=0.0)
                if isinstance(have, (int, float)) and isinstance(value, (int, float))
                and not isinstance(have, bool) else have == value)
        if not same:
            return f"{key} = {have!r}, not {value!r}"
    return None


def write_csv(path: str, rows: list[dict]) -> str:
    """Rows (dicts, union of their keys as header, None as an empty field) to ``path``."""
    os.makedirs(os.path.dirname(path) or ".", exist_ok=True)
    fields = list(dict.fromkeys(k for r in rows for k in r))
    with open(path, "w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=fields, restval="")
        writer.writeheader()
        writer.writerows([{k: ("" if v is None else v) for k, v in r.items()} for r in rows])
    return path
