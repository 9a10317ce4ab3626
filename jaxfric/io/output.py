"""The per-run output contract (outputs spec, schema_version 1): ``history.csv``, ``summary.json``,
``contact.npz`` and the figures ``forces.png``, ``contact.png``, ``mesh.png``.

Everything here runs on the host (NumPy) after a run. The derived keys of ``summary.json`` and the
instant rows of ``contact.npz`` are computed from the values *as written* to ``history.csv`` (the
``%.12g`` strings parsed back), so that the file set is consistent to round-off by construction.

Named instants and the steady drawing force follow the benchmarks spec (each scene's "Outputs"
paragraph and section 6). :func:`write_run` never loses data files to a plotting error: the data
files are written first, figure errors are recorded in ``summary.json`` ``message`` and re-raised at
the end as :class:`OutputError`.
"""

from __future__ import annotations

import datetime
import json
import math
import os
import re

import numpy as np

from ..numerics.results import band_widening, causes
from .instants import (
    TIME_TOL,
    column,
    phase_names,
    scene_module,
    select_instants,
    steady_drawing_force,
    steady_rows,
    steady_window,
)

__all__ = ["SCHEMA_VERSION", "REQUIRED_COLUMNS", "INT_COLUMNS", "ALGORITHM_EXTRAS", "GAP_NO_PROJECTION",
           "OutputError", "CHECKS", "error_estimate", "richardson_error", "history_table", "json_ready", "write_run",
           "format_title"]

SCHEMA_VERSION = 1

#: The 12 required columns of ``history.csv``, in order (outputs spec section 2).
REQUIRED_COLUMNS = ("step", "phase", "time", "drawing_displacement", "drawing_force", "clamping_force",
                    "tool_position", "max_penetration", "n_active", "n_slip", "newton_iters", "wall_s")

#: Columns written as integers (required and algorithm extras).
INT_COLUMNS = ("step", "n_active", "n_slip", "newton_iters", "cutbacks", "cut_codes", "n_aug", "lcp_pivots",
               "ssn_iters", "ssn_fallbacks")

#: Algorithm extras, in the order written (after the scene extras).
ALGORITHM_EXTRAS = ("cutbacks", "cut_codes", "n_aug", "lcp_pivots", "ssn_iters", "ssn_fallbacks")

GAP_NO_PROJECTION = 1e30  # mm; gap written for a pair with no projection (outputs spec section 4)
_NAME = re.compile(r"[a-z][a-z0-9_]*\Z")
# History keys of RunResult that are not observations (written under their contract names where it has them).
_RUN_KEYS = ("time", "phase", "phase_name", "newton_iters", "cutbacks", "cut_codes", "augmentations", "wall_s",
             "lcp_pivots", "ssn_iters", "ssn_fallbacks", "step", "predicted", "damping_energy")

class OutputError(RuntimeError):
    """Some output file could not be written; the data files that could be written are on disk."""


# ---- history.csv ------------------------------------------------------------------------------------

def _format(value, integer: bool) -> str:
    if integer:
        return str(int(value))
    return f"{float(value):.12g}"


def cutback_causes(cut_codes) -> dict:
    """summary.json's ``cutback_causes``: per cause (:func:`jaxfric.numerics.results.causes`), the number of
    steps with a failed attempt that ended so, read from history.csv's ``cut_codes`` (a step's bit mask:
    bit k set where one of its failed attempts ended with result code k)."""
    counts: dict[str, int] = {}
    for mask in cut_codes:
        for name in causes(mask):
            counts[name] = counts.get(name, 0) + 1
    return counts


def _extra_columns(history: dict) -> list:
    """(column name, values) of the scene extras: observations beyond the required columns, vectors
    split into ``name_0, name_1, ...``; names made contract-valid ([a-z][a-z0-9_]*)."""
    out = []
    for key, value in history.items():
        if key in _RUN_KEYS or key in REQUIRED_COLUMNS:
            continue
        value = np.asarray(value)
        name = re.sub(r"[^a-z0-9_]", "_", str(key).lower())
        if not _NAME.match(name):
            name = "x_" + name
        if value.ndim == 1:
            out.append((name, value))
        else:
            flat = value.reshape(value.shape[0], -1)
            out.extend((f"{name}_{i}", flat[:, i]) for i in range(flat.shape[1]))
    return out


def history_table(scene, result) -> tuple[list, list, dict]:
    """The ``history.csv`` table of a run.

    Returns:
        ``(columns, lines, values)``: the header names, the formatted rows (strings, without line
        ends), and per column the values as written (int, float or str, parsed back from the text).
    """
    h = result.history
    n = len(np.asarray(h["time"]))
    phases = phase_names(scene.name, h) if scene_module(scene.name) is not None else np.asarray(h["phase_name"])
    cols = {"step": np.arange(n), "phase": phases}
    for name in REQUIRED_COLUMNS[2:]:
        cols[name] = column(h, name)
    extras = _extra_columns(h)
    algo = [("cutbacks", h.get("cutbacks"))]
    if h.get("cut_codes") is not None:
        algo.append(("cut_codes", np.asarray(h["cut_codes"])))
    if scene.algorithm == "auglag":
        algo.append(("n_aug", h.get("augmentations")))
    algo += [(k, h.get(k)) for k in ("lcp_pivots", "ssn_iters", "ssn_fallbacks")]
    taken = set(REQUIRED_COLUMNS)
    for name, value in extras + [(k, v) for k, v in algo if v is not None]:
        if name in taken:
            continue
        taken.add(name)
        cols[name] = np.asarray(value)
    columns = list(cols)
    text = {}
    for name, value in cols.items():
        if len(value) != n:
            raise ValueError(f"history column {name!r} has {len(value)} rows, expected {n}")
        if name == "phase":
            text[name] = [str(v) for v in value]
        else:
            integer = name in INT_COLUMNS or value.dtype.kind in "iub"
            text[name] = [_format(v, integer) for v in value]
    lines = [",".join(text[c][i] for c in columns) for i in range(n)]
    values: dict[str, list] = {}  # column name -> its str, int or float values, by column
    for name in columns:
        if name == "phase":
            values[name] = list(text[name])
        elif name in INT_COLUMNS or cols[name].dtype.kind in "iub":
            values[name] = [int(s) for s in text[name]]
        else:
            values[name] = [float(s) for s in text[name]]
    return columns, lines, values


# ---- summary.json -----------------------------------------------------------------------------------

def json_ready(value):
    """Plain JSON values: NumPy scalars and arrays to Python, tuples to lists, non-finite to None."""
    if isinstance(value, dict):
        return {str(k): json_ready(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_ready(v) for v in value]
    if isinstance(value, np.ndarray):
        return json_ready(value.tolist())
    if hasattr(value, "shape") and hasattr(value, "dtype"):  # JAX array
        return json_ready(np.asarray(value).tolist())
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    if isinstance(value, (int, np.integer)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        return float(value) if math.isfinite(float(value)) else None
    if value is None or isinstance(value, str):
        return value
    return str(value)


def _device() -> str:
    import jax

    device = jax.devices()[0]
    return "cpu" if device.platform == "cpu" else str(getattr(device, "device_kind", device.platform))


def format_title(scene_name: str, variant: str, algorithm: str, tag: str | None = None) -> str:
    """Figure title ``<scene> / <variant> / <algorithm>[ / <tag>]`` (outputs spec section 5)."""
    parts = [scene_name, variant, algorithm] + ([tag] if tag else [])
    return " / ".join(parts)


SOLVER_RTOL = 1e-8  # Newton's relative residual tolerance (jaxfric.numerics.newton.NewtonOptions default)


def richardson_error(value: float, other: float, ratio: float) -> float:
    """Richardson's first-order estimate of the error of ``value`` (signed: ``value`` minus the limit) from
    a companion run ``other`` whose discretisation parameter (element length, increment, layer thickness)
    is ``ratio`` times the run's: with F = F* + C h, F - F* = (F - F_other) / (1 - ratio).

    ``ratio`` 2 (a coarser companion) gives F - F_other; 1/2 (a finer one) gives 2 (F - F_other). For an
    error that falls by a factor q >= 2 per halving of h, the finer companion's estimate lies between 1
    and 2 times the true error (2 (q - 1) / q of it), and the coarser one's is q - 1 times it, so only
    the finer companion bounds the error within a factor of 2 when the order is unknown.
    """
    if ratio <= 0 or ratio == 1 or not math.isfinite(ratio):
        raise ValueError(f"field 'ratio' must be a finite number > 0 other than 1, got {ratio!r}")
    return (value - other) / (1.0 - ratio)


#: The discretisation components a companion run estimates: name -> what it varies, for the method text.
CHECKS = {"step": "the nominal increments", "mesh": "the elements along the strip",
          "layers": "the elements through the thickness"}


def error_estimate(scene, values: dict, window, steady, penalty_tangent=None, checks=None) -> dict:
    """An a-posteriori estimate of the error of the run's main output, from this run and its companions.

    The main output is the steady drawing force F̄ (the peak drawing force where no steady value
    exists). Relative contributions, combined in quadrature:

    - ``contact``: the largest penetration over the run divided by the modelled sheet thickness (the
      half thickness where a scene uses symmetry). A penetration
      delta shifts the strip's path through the tools by delta, and the bending and friction work that
      make the drawing force scale with the thickness (force ~ t^2 / R for bending, the path for
      friction), so delta / t is the order of the relative force error. It is what separates a penalty
      run from the exact contact (LCP) answer; it vanishes as eps_n grows or the AL target shrinks.
    - ``scatter``: the standard deviation of the drawing force over the steady window divided by F̄:
      the force oscillates as the nodes pass the tools, which measures the mesh and step resolution
      of the steady regime (absent for the peak force).
    - ``solver``: Newton's relative residual tolerance.
    - ``penalty`` (only with ``penalty_tangent``, eps_N dF/d eps_N per row from
      :func:`jaxfric.identification.accuracy.penalty_tangent`; ``jaxfric run --error-estimate sensitivity``):
      |eps_N dF̄/d eps_N| / |F̄|, the penalty's share. Where the sheet is stiff across its thickness the
      penetration is tiny although the penalty's compliance sets the force (flat die with the die held
      in place: ``contact`` 1.1e-5 against a measured error of 0.74 at eps_N = 1e5), which this term sees.
    - ``step``, ``mesh``, ``layers`` (only with ``checks``: name -> a companion run from
      :func:`jaxfric.identification.accuracy.step_check`, ``mesh_check`` or ``layers_check``, whose
      ``"ratio"`` is its increment, element length or layer thickness over the run's; ``jaxfric run
      --error-estimate step,mesh_fine,layers``): |:func:`richardson_error`| / |F̄|, the first-order
      estimate of that discretisation's error. A finer companion (ratio 1/2) gives 1 to 2 times the error
      wherever it falls at least in half per halving; a coarser one (``--error-estimate mesh``, ratio 2)
      costs half the run but is q - 1 times the error for a ratio q of successive changes, so it
      overstates the error where the coarser mesh is not yet in the asymptotic range (docs/results.md,
      estimates against the true error). ``step`` sees the step error only where halving the nominal
      increments halves the steps: where the controller's cuts set them (a stiff penalty), the two runs
      take nearly the same steps (``step_check.n_steps`` tells). Each companion's record
      ``<name>_check`` keeps its value, steps, mesh, ratio and signed share (``signed``).

    ``not_estimated`` lists the discretisation components the run did not estimate.

    This is an indicator, not a bound; ``experiments/error_estimates.py`` compares it with the error
    against converged references.
    """
    nodes = np.asarray(scene.model.mesh.nodes)
    left = np.asarray(scene.model.mesh.left)
    thickness = float(np.ptp(nodes[left, 1])) or 1.0
    force = np.asarray(values["drawing_force"], dtype=np.float64)
    parts = {"contact": float(max(values["max_penetration"])) / thickness, "solver": SOLVER_RTOL}
    if steady is not None:
        quantity, value = "steady_drawing_force", float(steady)
        rows = steady_rows(values["phase"], values["drawing_displacement"], window)
        parts["scatter"] = float(np.std(force[rows])) / abs(value) if value else 0.0
    else:
        quantity, value = "peak_drawing_force", float(np.max(force))
    method = ("quadrature sum of max_penetration / thickness, steady-window force scatter / mean, and the "
              "Newton tolerance")
    if penalty_tangent is not None:
        tangent = np.asarray(penalty_tangent, dtype=np.float64)
        if steady is not None:
            change = steady_drawing_force({"phase": values["phase"], "drawing_displacement":
                                           values["drawing_displacement"], "drawing_force": tangent}, window)
            # ``steady`` is the steady force over the same rows and window, so it exists here too.
            assert change is not None
        else:
            change = float(tangent[int(np.argmax(force))])
        parts["penalty"] = abs(change) / abs(value) if value else 0.0
        method += ", and |eps_N dF/d eps_N| / F (forward mode along the run)"
    extra: dict = {}
    for name, check in (checks or {}).items():
        if name not in CHECKS:
            raise ValueError(f"field 'checks': unknown component {name!r} (one of {', '.join(CHECKS)})")
        other = check["steady"] if steady is not None else check["peak"]
        if other is None:
            raise ValueError(f"field 'checks': the {name} companion has no steady drawing force")
        ratio = float(check["ratio"])
        signed = richardson_error(value, other, ratio) / abs(value) if value else 0.0
        parts[name] = abs(signed)
        method += f", and Richardson's first-order error from {CHECKS[name]} times {ratio:g}"
        extra[f"{name}_check"] = {"value": float(other), "n_steps": int(check["n_steps"]),
                                  "mesh": list(check["mesh"]), "ratio": ratio, "signed": signed}
    extra["not_estimated"] = [k for k in CHECKS if k not in parts]
    relative = math.sqrt(math.fsum(v * v for v in parts.values()))
    return {"quantity": quantity, "value": value, "relative": relative, "absolute": relative * abs(value),
            "components": parts, "method": method + " (jaxfric.io.output.error_estimate)", **extra}


def _summary(scene, result, tag, values, instants, fallback, window, steady, notes, penalty_tangent=None,
             checks=None) -> dict:
    import jax

    n_rows = len(values["step"])
    n_steps = n_rows - 1
    n_phases = len(scene.phase_names)
    converged = abs(values["time"][-1] - n_phases) <= TIME_TOL
    message_parts = []
    if not converged:
        message_parts.append(result.message or "the run stopped before the end of its last phase")
    elif not result.converged:
        message_parts.append(f"solver reported failure after completing all phases: {result.message}")
    message_parts += [n for n in notes if n]
    parameters = json_ready(dict(scene.parameters))
    mesh = [int(scene.model.mesh.nx), int(scene.model.mesh.ny)]
    parameters.setdefault("mesh", {"nx": mesh[0], "ny": mesh[1]})
    mean_aug = None
    if scene.algorithm == "auglag" and "n_aug" in values and n_steps > 0:
        mean_aug = float(sum(values["n_aug"])) / n_steps
    return {
        "schema_version": SCHEMA_VERSION,
        "scene": scene.name,
        "variant": scene.variant,
        "algorithm": scene.algorithm,
        "tag": tag,
        "parameters": parameters,
        "mesh": mesh,
        "n_steps": n_steps,
        "newton_iters_total": int(sum(values["newton_iters"])),
        "n_cutbacks": int(sum(values.get("cutbacks", [0]))),
        "cutback_causes": cutback_causes(values.get("cut_codes", [])),
        "wall_s": float(math.fsum(values["wall_s"])),
        "compile_s": max(float(result.compile_s), 0.0),
        "cpu_s": float(result.cpu_s),
        "converged": bool(converged),
        "message": "; ".join(message_parts),
        "max_penetration": float(max(values["max_penetration"])),
        "steady_window": [float(window[0]), float(window[1])],
        "steady_drawing_force": steady,
        "peak_drawing_force": float(max(values["drawing_force"])),
        "final_clamping_force": float(values["clamping_force"][-1]),
        "instants": list(instants),
        "instants_fallback": list(fallback),
        "mean_augmentations": mean_aug,
        "error_estimate": error_estimate(scene, values, window, steady, penalty_tangent, checks),
        "dtype": "float64",
        "device": _device(),
        "run_devices": int(result.devices),
        "jax_version": jax.__version__,
        "created_utc": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
    }


def damping_note(energy, values: dict) -> str:
    """The summary's note on the stabilised steps (:class:`jaxfric.loadpath.controller.StepControl`,
    ``stabilize``): how many, and the energy their damper took against the drawing force's work,
    the integral of ``drawing_force`` over ``drawing_displacement``; "" where there are none."""
    energy = np.asarray(energy, float)
    n = int(np.count_nonzero(energy))
    if n == 0:
        return ""
    total = float(energy.sum())
    work = float(np.trapezoid(values["drawing_force"], values["drawing_displacement"]))
    share = f", {100 * total / work:.2g} % of the drawing force's work ({work:.4g} N mm/mm)" if work > 0 else ""
    return (f"{n} step{'s' if n != 1 else ''} stabilised (history damping_energy): the damper took "
            f"{total:.3g} N mm/mm{share}")


def band_note(widened) -> str:
    """The summary's note on exact contact's proximity band grown during the run (``RunResult.band_widened``:
    (pseudo-time, band) pairs); "" where it kept its size."""
    if not widened:
        return ""
    grown = ", ".join(band_widening(t, band) for t, band in widened)
    return f"exact contact's proximity band widened (the contact zone outgrew it: Result.BAND_FULL) {grown}"


def _write_summary(path: str, summary: dict) -> None:
    text = json.dumps(json_ready(summary), indent=2, allow_nan=False)
    _write_text(path, text + "\n")


def _write_text(path: str, text: str) -> None:
    tmp = path + ".tmp"
    with open(tmp, "w", encoding="utf-8", newline="\n") as f:
        f.write(text)
    os.replace(tmp, path)


# ---- contact.npz ------------------------------------------------------------------------------------

def _pair_arrays(model) -> tuple[np.ndarray, np.ndarray]:
    sizes = [len(t.candidates) for t in model.tools]
    node = (np.concatenate([np.asarray(t.candidates) for t in model.tools]) if model.tools
            else np.zeros(0)).astype(np.int64)
    tool = np.repeat(np.arange(len(sizes)), sizes).astype(np.int64)
    return node, tool


def contact_arrays(scene, result, names, rows, values) -> dict:
    """The arrays of ``contact.npz`` (outputs spec section 4) for instants ``names`` at history
    ``rows``, from ``result.snapshots``; ``values`` are the history columns as written."""
    model = scene.model
    pair_node, pair_tool = _pair_arrays(model)
    m, n_tools = pair_node.size, len(model.tools)
    n_nodes, n_el = model.mesh.n_nodes, model.mesh.n_elements
    out = {
        "instant_names": np.array(list(names), dtype=str).astype("U"),
        "instant_steps": np.asarray(rows, dtype=np.int64),
        "instant_drawing_displacement": np.array([values["drawing_displacement"][r] for r in rows],
                                                 dtype=np.float64),
        "x0": np.asarray(model.mesh.nodes, dtype=np.float64),
        "elements": np.asarray(model.mesh.elements, dtype=np.int64),
        "tool_names": np.array(list(scene.tool_names), dtype=str).astype("U"),
        "pair_node": pair_node,
        "pair_tool": pair_tool,
    }
    shapes = {"x": (n_nodes, 2), "eqps": (n_el,), "rn": (m,), "rt": (m,), "normal": (m, 2), "gap": (m,),
              "mu": (m,), "status": (m,), "tool_offset": (n_tools, 2)}
    for name, row in zip(names, rows):
        if row not in result.snapshots:
            raise KeyError(f"no snapshot for history row {row} (instant {name!r}); run with "
                           f"snapshot=scene.snapshot")
        snap = result.snapshots[row]
        for key, shape in shapes.items():
            value = np.asarray(snap[key])
            if key == "eqps" and value.ndim == 2:  # per Gauss point: element mean
                value = value.mean(axis=1)
            if key == "status":
                value = value.astype(np.int8)
            else:
                value = value.astype(np.float64)
                if key == "gap":  # "no projection" is 1e30, never inf
                    value = np.where(np.isfinite(value), np.minimum(value, GAP_NO_PROJECTION),
                                     GAP_NO_PROJECTION)
            out[f"{name}__{key}"] = value.reshape(shape)
    return out


# ---- the run directory ------------------------------------------------------------------------------

def write_run(scene, result, out_dir, tag: str | None = None, figures: bool = True,
              penalty_tangent=None, checks=None) -> dict:
    """Write the run directory of ``result`` (outputs spec): six files, also for a failed run.

    Order: ``history.csv``, ``summary.json``, ``contact.npz``, then the figures. A failure in a later
    file never loses the earlier ones; it is recorded in ``summary.json`` ``message`` (rewritten) and
    raised at the end as :class:`OutputError`.

    Args:
        scene: the :class:`~jaxfric.scenes.base.Scene` that was run.
        result: its :class:`~jaxfric.loadpath.run.RunResult`, run with ``snapshot=scene.snapshot``.
        out_dir: the run directory (created).
        tag: study tag (regex ``[A-Za-z0-9][A-Za-z0-9._+-]*``) or None.
        figures: write the three PNG figures (False only for tests of the data files).
        penalty_tangent: optional eps_N dF/d eps_N per history row
            (:func:`jaxfric.identification.accuracy.penalty_tangent`), adding the penalty's share to ``error_estimate``.
        checks: optional companion runs, ``{"step" | "mesh" | "layers": result}`` of
            :func:`jaxfric.identification.accuracy.step_check`, ``mesh_check`` or ``layers_check``, adding
            that discretisation's share to ``error_estimate``.

    Returns:
        the ``summary.json`` object.
    """
    if tag is not None and not re.fullmatch(r"[A-Za-z0-9][A-Za-z0-9._+-]*", tag):
        raise ValueError(f"field 'tag' must match [A-Za-z0-9][A-Za-z0-9._+-]*, got {tag!r}")
    try:
        os.makedirs(out_dir, exist_ok=True)
    except OSError as err:
        raise OutputError(f"run directory {out_dir} cannot be created: {err.strerror or err}") from None
    columns, lines, values = history_table(scene, result)
    text = ",".join(columns) + "\n" + "".join(line + "\n" for line in lines)
    _write_text(os.path.join(out_dir, "history.csv"), text)

    notes = []
    bad = [c for c in columns if c != "phase" and not all(math.isfinite(v) for v in values[c])]
    if bad:
        notes.append(f"non-finite values in history columns {', '.join(bad)}")
    if scene_module(scene.name) is not None:
        names, rows, fallback = select_instants(scene.name, {**values, "phase_name": values["phase"]})
    else:
        names, rows, fallback = ["final"], [len(lines) - 1], []
    window, note = steady_window(scene.name, values, scene.steady_window)
    notes.append(note)
    notes.append(damping_note(result.history.get("damping_energy", ()), values))
    notes.append(band_note(result.band_widened))
    steady = steady_drawing_force({**values, "phase_name": values["phase"]}, window)
    summary = _summary(scene, result, tag, values, names, fallback, window, steady, notes, penalty_tangent,
                       checks)
    summary_path = os.path.join(out_dir, "summary.json")
    _write_summary(summary_path, summary)

    errors = []
    contact = None
    try:
        contact = contact_arrays(scene, result, names, rows, values)
        tmp = os.path.join(out_dir, "contact.tmp.npz")
        np.savez_compressed(tmp, **contact)
        os.replace(tmp, os.path.join(out_dir, "contact.npz"))
    except Exception as err:  # noqa: BLE001 - recorded, re-raised below
        errors.append(f"contact.npz not written: {type(err).__name__}: {err}")
    if figures:
        from . import figures as fig

        title = format_title(scene.name, scene.variant, scene.algorithm, tag)
        jobs = [("forces.png", lambda p: fig.forces_figure(p, title, scene.name, values, summary,
                                                           len(scene.phase_names)))]
        if contact is not None:
            outlines = _tool_outlines(scene, contact)
            jobs += [("contact.png", lambda p: fig.contact_figure(p, title, contact, outlines, scene.roi,
                                                                  scene.y_scale)),
                     ("mesh.png", lambda p: fig.mesh_figure(p, title, contact, outlines, scene.roi,
                                                            scene.y_scale))]
        else:
            errors += ["contact.png not drawn: no contact data", "mesh.png not drawn: no contact data"]
        for name, job in jobs:
            try:
                job(os.path.join(out_dir, name))
            except Exception as err:  # noqa: BLE001 - recorded, re-raised below
                errors.append(f"{name} not drawn: {type(err).__name__}: {err}")
    if errors:
        summary["message"] = "; ".join([m for m in (summary["message"], *errors) if m])
        _write_summary(summary_path, summary)
        raise OutputError(f"run directory {out_dir} is incomplete: " + "; ".join(errors))
    return summary


def _tool_outlines(scene, contact: dict) -> dict:
    """Per instant, the (k, 2) outline of every tool at that instant's offset (mm)."""
    from ..contact.tools import tool_outline

    out = {}
    for name in contact["instant_names"]:
        offsets = contact[f"{name}__tool_offset"]
        out[str(name)] = [np.asarray(tool_outline(t.geometry, offsets[k], 64))
                          for k, t in enumerate(scene.model.tools)]
    return out
