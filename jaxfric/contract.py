"""Independent checker of a run directory against the output contract (outputs spec section 6).

:func:`check_run_dir` reads only the files (no jaxfric run objects) and returns the list of
violations, each a one-line string naming the file and the rule; an empty list means the directory
satisfies the contract. The scene metadata it needs (identifiers, phases, instants, tools, clamping
tool and its closing direction, default steady windows) is restated here from the benchmarks spec on
purpose, so that the writer (:mod:`jaxfric.output`) is checked against the spec and not against itself.

Run as ``python -m jaxfric.contract DIR [DIR ...]``.
"""

from __future__ import annotations

import datetime
import json
import math
import os
import re
import struct
import sys
import zipfile
from collections.abc import Callable
from typing import Any

import numpy as np

from .formulations import ALGORITHMS

__all__ = ["check_run_dir", "FILES", "SCENES"]

FILES = ("history.csv", "summary.json", "contact.npz", "forces.png", "contact.png", "mesh.png")
REQUIRED = ("step", "phase", "time", "drawing_displacement", "drawing_force", "clamping_force",
            "tool_position", "max_penetration", "n_active", "n_slip", "newton_iters", "wall_s")
_INT_REQUIRED = ("step", "n_active", "n_slip", "newton_iters")
_INT_EXTRAS = ("cutbacks", "n_aug", "lcp_pivots", "ssn_iters", "ssn_fallbacks")

# Per scene: variants, phases, instants, tools, (clamping tool, e_q), default steady window (mm).
SCENES: dict[str, dict[str, Any]] = {
    "flat_die": dict(variants=("const_force", "const_position"), phases=("clamp", "draw"),
                     instants=("clamped", "intermediate", "sliding", "final"), tools=("die",),
                     clamp=("die", (0.0, -1.0)), window=(0.02, 0.03)),
    "bead": dict(variants=tuple(f"th{t}_mu{m}" for m in ("000", "017") for t in ("045", "090", "135")),
                 phases=("clamp", "wind", "draw"), instants=("clamped", "folded", "drawing", "final"),
                 tools=("die_up", "die_lo", "roller"), clamp=("die_up", (0.0, -1.0)), window=(4.0, 8.0)),
    "nine": dict(variants=("mu000", "mu017"), phases=("clamp", "draw"),
                 instants=("clamped", "steady", "final"), tools=("A", "B", "C", "D", "E"),
                 clamp=("B", (0.0, -1.0)), window=(20.0, 35.0)),
    "blankholder": dict(variants=tuple(f"shape{k}" for k in range(1, 10)), phases=("close", "lock", "draw"),
                        instants=("closed", "locked", "drawing", "final"), tools=("upper", "lower"),
                        clamp=("lower", (0.0, 1.0)), window=(35.0, 55.0)),
}
# Instants at the end of a phase, and "closest to" instants (phase, drawing displacement in mm).
_END_OF = {"clamped": "clamp", "folded": "wind", "closed": "close", "locked": "lock"}
_CLOSEST = {("bead", "drawing"): 4.0, ("nine", "steady"): 27.5, ("blankholder", "drawing"): 27.5}

_TAG = re.compile(r"[A-Za-z0-9][A-Za-z0-9._+-]*\Z")
_NAME = re.compile(r"[a-z][a-z0-9_]*\Z")
_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_RTOL, _ATOL = 1e-9, 1e-12       # summary vs history (outputs spec section 3)
_RTOL_NPZ = 1e-6                 # contact.npz vs history (outputs spec section 4)
_STEADY_TOL = 1e-9               # mm (benchmarks spec section 6)
_TIME_TOL = 1e-9


def _close(a, b, rtol=_RTOL, atol=_ATOL) -> bool:
    return abs(a - b) <= atol + rtol * max(abs(a), abs(b))


def _is_number(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def _is_int(v) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


# ---- 1. directory and PNGs ------------------------------------------------------------------------

def _check_files(path: str, out: list) -> None:
    for name in FILES:
        p = os.path.join(path, name)
        if not os.path.isfile(p):
            out.append(f"{name}: missing")
        elif os.path.getsize(p) == 0:
            out.append(f"{name}: empty")
        elif name.endswith(".png"):
            with open(p, "rb") as f:
                head = f.read(24)
            if head[:8] != _PNG_SIGNATURE or head[12:16] != b"IHDR":
                out.append(f"{name}: not a PNG (bad signature or no IHDR header)")
                continue
            width, height = struct.unpack(">II", head[16:24])
            if width < 800 or height < 500:
                out.append(f"{name}: {width} x {height} px, at least 800 x 500 required")


# ---- 2. history.csv -------------------------------------------------------------------------------

def _read_history(path: str, scene: dict | None, out: list) -> dict | None:
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
        if not _NAME.match(name):
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
        if name in _INT_REQUIRED or name in _INT_EXTRAS:
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
        if abs(cols[name][0]) > _ATOL:
            out.append(f"history.csv: '{name}' must be 0 on row 0 (initial state)")
    if any(v < 0 for v in cols["max_penetration"]):
        out.append("history.csv: 'max_penetration' < 0")
    if any(s < 0 or s > a for a, s in zip(cols["n_active"], cols["n_slip"])):
        out.append("history.csv: 0 <= n_slip <= n_active violated")
    if any(v < 0 for v in cols["newton_iters"]):
        out.append("history.csv: 'newton_iters' < 0")
    if any(v < 0 for v in cols["wall_s"]):
        out.append("history.csv: 'wall_s' < 0")
    for name in _INT_EXTRAS:
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
            if not all(-_TIME_TOL <= t <= len(phases) + _TIME_TOL for t in time):
                out.append(f"history.csv: 'time' outside [0, {len(phases)}]")
            if not all(k - _TIME_TOL <= t <= k + 1 + _TIME_TOL for k, t in zip(index, time)):
                out.append("history.csv: 'time' of a row outside its phase interval [k-1, k]")
            u = cols["drawing_displacement"]
            draw = [i for i, p in enumerate(cols["phase"]) if p == "draw"]
            first = draw[0] if draw else n
            if any(u[i] != 0.0 for i in range(first)):
                out.append("history.csv: 'drawing_displacement' must be 0 before the first draw row")
            if any(u[b] < u[a] for a, b in zip(draw, draw[1:])):
                out.append("history.csv: 'drawing_displacement' decreases on draw rows")
    return cols


def _steady(cols: dict, window) -> float | None:
    """Steady drawing force (benchmarks spec section 6), recomputed from the history."""
    a, b = window
    idx = [i for i, p in enumerate(cols["phase"])
           if p == "draw" and a - _STEADY_TOL <= cols["drawing_displacement"][i] <= b + _STEADY_TOL]
    if len(idx) < 2:
        return None
    u = [cols["drawing_displacement"][i] for i in idx]
    f = [cols["drawing_force"][i] for i in idx]
    span = u[-1] - u[0]
    if span <= 0 or span < 0.5 * (b - a):
        return None
    return sum(0.5 * (f[k] + f[k + 1]) * (u[k + 1] - u[k]) for k in range(len(u) - 1)) / span


# ---- 3. summary.json ------------------------------------------------------------------------------

def _reject_constant(name):
    raise ValueError(f"non-finite number {name}")


def _read_summary(path: str, out: list) -> dict | None:
    p = os.path.join(path, "summary.json")
    if not os.path.isfile(p) or os.path.getsize(p) == 0:
        return None
    try:
        with open(p, encoding="utf-8") as f:
            summary = json.load(f, parse_constant=_reject_constant)
    except ValueError as err:
        out.append(f"summary.json: not valid JSON with finite numbers ({err})")
        return None
    if not isinstance(summary, dict):
        out.append("summary.json: not a JSON object")
        return None
    return summary


_SUMMARY_TYPES = {
    "schema_version": "int", "scene": "str", "variant": "str", "algorithm": "str", "tag": "str|null",
    "parameters": "object", "mesh": "int2", "n_steps": "int", "newton_iters_total": "int",
    "n_cutbacks": "int", "wall_s": "float", "compile_s": "float", "converged": "bool", "message": "str",
    "max_penetration": "float", "steady_window": "float2", "steady_drawing_force": "float|null",
    "peak_drawing_force": "float", "final_clamping_force": "float", "instants": "strlist",
    "instants_fallback": "strlist", "mean_augmentations": "float|null", "error_estimate": "object", "dtype": "str",
    "device": "str", "jax_version": "str", "created_utc": "str",
}


def _scene(name: Any) -> dict[str, Any] | None:
    """The metadata of the scene ``name`` (any value read from summary.json); None if it names no scene."""
    return SCENES.get(name)


def _check_error_estimate(get) -> list:
    """error_estimate: the main output's value and a finite, non-negative relative error."""
    est = get("error_estimate")
    if not isinstance(est, dict):
        return []
    keys = ("quantity", "value", "relative", "absolute", "components")
    missing = [k for k in keys if k not in est]
    if missing:
        return [f"summary.json: error_estimate lacks {', '.join(missing)}"]
    if est["quantity"] not in ("steady_drawing_force", "peak_drawing_force"):
        return [f"summary.json: error_estimate quantity {est['quantity']!r} is not a drawing force"]
    rel = est["relative"]
    if not (_is_number(rel) and math.isfinite(rel) and rel >= 0):
        return ["summary.json: error_estimate relative must be a finite number >= 0"]
    if _is_number(get(est["quantity"])) and not _close(est["value"], get(est["quantity"])):
        return [f"summary.json: error_estimate value != {est['quantity']}"]
    return []


def _type_ok(value, kind: str) -> bool:
    if kind.endswith("|null"):
        return value is None or _type_ok(value, kind[:-5])
    return {
        "int": lambda v: _is_int(v),
        "float": lambda v: _is_number(v),
        "str": lambda v: isinstance(v, str),
        "bool": lambda v: isinstance(v, bool),
        "object": lambda v: isinstance(v, dict),
        "int2": lambda v: isinstance(v, list) and len(v) == 2 and all(_is_int(x) for x in v),
        "float2": lambda v: isinstance(v, list) and len(v) == 2 and all(_is_number(x) for x in v),
        "strlist": lambda v: isinstance(v, list) and all(isinstance(x, str) for x in v),
    }[kind](value)


def _check_summary(s: dict, cols: dict | None, out: list) -> None:
    for key, kind in _SUMMARY_TYPES.items():
        if key not in s:
            out.append(f"summary.json: missing key {key!r}")
        elif not _type_ok(s[key], kind):
            out.append(f"summary.json: key {key!r} must be {kind}, got {s[key]!r:.60}")
    get: Callable[[str], Any] = s.get  # the value of a key, of any JSON type, or None
    if get("schema_version") != 1:
        out.append("summary.json: schema_version must be 1")
    scene = _scene(get("scene"))
    if scene is None:
        out.append(f"summary.json: unknown scene {get('scene')!r}")
    elif get("variant") not in scene["variants"]:
        out.append(f"summary.json: unknown variant {get('variant')!r} for scene {get('scene')!r}")
    if get("algorithm") not in ALGORITHMS:
        out.append(f"summary.json: unknown algorithm {get('algorithm')!r}")
    if isinstance(get("tag"), str) and not _TAG.match(get("tag")):
        out.append(f"summary.json: tag {get('tag')!r} does not match [A-Za-z0-9][A-Za-z0-9._+-]*")
    if get("dtype") != "float64":
        out.append("summary.json: dtype must be 'float64'")
    if isinstance(get("device"), str) and not get("device"):
        out.append("summary.json: device is empty")
    if isinstance(get("created_utc"), str):
        try:
            datetime.datetime.fromisoformat(get("created_utc"))
        except ValueError:
            out.append("summary.json: created_utc is not an ISO-8601 timestamp")
    _check_parameters(s, out)
    if _is_number(get("compile_s")) and get("compile_s") < 0:
        out.append("summary.json: compile_s < 0")
    if scene is not None and _type_ok(get("instants"), "strlist"):
        names = get("instants")
        if any(n not in scene["instants"] for n in names) or \
                [n for n in scene["instants"] if n in names] != names:
            out.append(f"summary.json: instants {names} not a subsequence of {list(scene['instants'])}")
        if "final" not in names:
            out.append("summary.json: instants must include 'final'")
        if _type_ok(get("instants_fallback"), "strlist") and any(n not in names for n in get("instants_fallback")):
            out.append("summary.json: instants_fallback must be a subset of instants")
    if _type_ok(get("steady_window"), "float2") and get("steady_window")[0] > get("steady_window")[1]:
        out.append("summary.json: steady_window must have a <= b")
    if scene is not None and _type_ok(get("steady_window"), "float2") and not get("message"):
        configured = [tuple(w) for w in _find_key(get("parameters"), "steady_window")
                      if isinstance(w, list) and len(w) == 2]
        if tuple(get("steady_window")) not in [scene["window"], *configured]:
            out.append("summary.json: steady_window is neither the scene default nor the configured "
                       "window, and message does not say why")
    if cols is None:
        return
    n = len(cols["step"])
    checks = [
        ("n_steps", n - 1, True),
        ("newton_iters_total", sum(cols["newton_iters"]), True),
        ("n_cutbacks", sum(cols.get("cutbacks", [0])), True),
        ("wall_s", math.fsum(cols["wall_s"]), False),
        ("max_penetration", max(cols["max_penetration"]), False),
        ("peak_drawing_force", max(cols["drawing_force"]), False),
        ("final_clamping_force", cols["clamping_force"][-1], False),
    ]
    for key, expected, exact in checks:
        value = get(key)
        if not _is_number(value):
            continue
        if (value != expected) if exact else not _close(value, expected):
            out.append(f"summary.json: {key} = {value!r} but history.csv gives {expected!r}")
    if scene is not None:
        done = abs(cols["time"][-1] - len(scene["phases"])) <= _TIME_TOL
        if isinstance(get("converged"), bool) and get("converged") != done:
            out.append(f"summary.json: converged = {get('converged')} but the last row's time is "
                       f"{cols['time'][-1]!r} of {len(scene['phases'])} phases")
    if get("converged") is False and not get("message"):
        out.append("summary.json: message must give the reason when converged is false")
    if _type_ok(get("steady_window"), "float2") and _type_ok(get("steady_drawing_force"), "float|null"):
        expected = _steady(cols, get("steady_window"))
        value = get("steady_drawing_force")
        if (expected is None) != (value is None) or (value is not None and not _close(value, expected)):
            out.append(f"summary.json: steady_drawing_force = {value!r}, recomputed from history.csv "
                       f"and steady_window: {expected!r}")
    if get("algorithm") == "auglag":
        if "n_aug" not in cols:
            out.append("history.csv: column 'n_aug' is required for auglag")
        elif _is_number(get("mean_augmentations")) and n > 1 and \
                not _close(get("mean_augmentations"), sum(cols["n_aug"]) / (n - 1)):
            out.append("summary.json: mean_augmentations != sum(n_aug) / n_steps")
        elif get("mean_augmentations") is None and n > 1:
            out.append("summary.json: mean_augmentations must be a number for auglag")
    elif get("mean_augmentations") is not None:
        out.append("summary.json: mean_augmentations must be null unless auglag")
    out += _check_error_estimate(get)


def _find_key(obj, key: str) -> list:
    """Every value stored under ``key`` anywhere in a JSON object."""
    found = []
    if isinstance(obj, dict):
        for k, v in obj.items():
            if k == key:
                found.append(v)
            found += _find_key(v, key)
    elif isinstance(obj, list):
        for v in obj:
            found += _find_key(v, key)
    return found


def _check_parameters(s: dict, out: list) -> None:
    p = s.get("parameters")
    if not isinstance(p, dict):
        return
    need = {"geometry": (), "material": ("E", "nu", "sigma_y", "A", "n"), "friction": (),
            "contact": ("eps_n", "eps_t", "target_gap", "d_capture"), "mesh": ("nx", "ny"), "schedule": ()}
    for obj, keys in need.items():
        if obj not in p:
            out.append(f"summary.json: parameters.{obj} missing")
            continue
        if obj != "schedule" and not isinstance(p[obj], dict):
            out.append(f"summary.json: parameters.{obj} must be an object")
            continue
        for key in keys:
            if key not in p[obj]:
                out.append(f"summary.json: parameters.{obj}.{key} missing")
    contact = p.get("contact")
    if isinstance(contact, dict) and "target_gap" in contact:
        if s.get("algorithm") != "auglag" and contact["target_gap"] is not None:
            out.append("summary.json: parameters.contact.target_gap must be null unless auglag")
        if s.get("algorithm") == "auglag" and not _is_number(contact["target_gap"]):
            out.append("summary.json: parameters.contact.target_gap must be a number for auglag")
    mesh = p.get("mesh")
    if isinstance(mesh, dict) and isinstance(s.get("mesh"), list) and \
            [mesh.get("nx"), mesh.get("ny")] != s["mesh"]:
        out.append(f"summary.json: mesh {s['mesh']} differs from parameters.mesh {mesh}")


# ---- 4. contact.npz -------------------------------------------------------------------------------

def _check_contact(path: str, s: dict | None, cols: dict | None, out: list) -> None:
    p = os.path.join(path, "contact.npz")
    if not os.path.isfile(p) or os.path.getsize(p) == 0:
        return
    try:
        with np.load(p, allow_pickle=False) as f:
            data = {k: f[k] for k in f.files}
    except (ValueError, OSError, zipfile.BadZipFile) as err:
        out.append(f"contact.npz: cannot be read with allow_pickle=False ({err})")
        return
    top = {"instant_names": "U", "instant_steps": "int64", "instant_drawing_displacement": "float64",
           "x0": "float64", "elements": "int64", "tool_names": "U", "pair_node": "int64", "pair_tool": "int64"}
    for key, dtype in top.items():
        if key not in data:
            out.append(f"contact.npz: missing {key!r}")
        elif (data[key].dtype.kind != "U") if dtype == "U" else (data[key].dtype != np.dtype(dtype)):
            out.append(f"contact.npz: {key!r} has dtype {data[key].dtype}, expected {dtype}")
    if any(k not in data for k in top):
        return
    names = [str(n) for n in data["instant_names"]]
    k = len(names)
    x0, elements = data["x0"], data["elements"]
    n_tools, m = data["tool_names"].shape[0], data["pair_node"].shape[0]
    shapes = {"instant_names": (k,), "instant_steps": (k,), "instant_drawing_displacement": (k,),
              "tool_names": (n_tools,), "pair_node": (m,), "pair_tool": (m,)}
    ok = True
    for key, shape in shapes.items():
        if data[key].shape != shape:
            out.append(f"contact.npz: {key!r} has shape {data[key].shape}, expected {shape}")
            ok = False
    if x0.ndim != 2 or x0.shape[1] != 2 or elements.ndim != 2 or elements.shape[1] != 4:
        out.append(f"contact.npz: x0 {x0.shape} / elements {elements.shape} must be (n_nodes, 2) / (n_el, 4)")
        return
    n_nodes, n_el = x0.shape[0], elements.shape[0]
    if not np.all(np.isfinite(x0)):
        out.append("contact.npz: x0 has non-finite values")
    if s is not None and isinstance(s.get("mesh"), list) and len(s["mesh"]) == 2:
        nx, ny = s["mesh"]
        if _is_int(nx) and _is_int(ny) and ((nx + 1) * (ny + 1), nx * ny) == (n_nodes, n_el):
            i_grid, j_grid = np.meshgrid(np.arange(nx), np.arange(ny), indexing="ij")
            i, j = i_grid.ravel(), j_grid.ravel()
            node = lambda a, b: a * (ny + 1) + b  # noqa: E731
            expected = np.stack([node(i, j), node(i + 1, j), node(i + 1, j + 1), node(i, j + 1)], axis=1)
            if not np.array_equal(elements, expected):
                out.append("contact.npz: elements do not follow the numbering of benchmarks spec section 0")
        else:
            out.append(f"contact.npz: {n_nodes} nodes / {n_el} elements do not match mesh {s['mesh']}")
    if n_el and np.all(elements >= 0) and np.all(elements < n_nodes):
        q = x0[elements]
        x, y = q[:, :, 0], q[:, :, 1]  # shoelace formula: positive area = counter-clockwise
        area = 0.5 * np.sum(x * np.roll(y, -1, axis=1) - np.roll(x, -1, axis=1) * y, axis=1)
        if np.any(area <= 0):
            out.append("contact.npz: elements must be counter-clockwise in x0")
    else:
        out.append("contact.npz: element node indices out of range")
    if np.any((data["pair_node"] < 0) | (data["pair_node"] >= n_nodes)):
        out.append("contact.npz: pair_node out of range")
    if np.any((data["pair_tool"] < 0) | (data["pair_tool"] >= n_tools)):
        out.append("contact.npz: pair_tool out of range")
        ok = False
    scene = _scene(s.get("scene")) if s is not None else None
    tools = [str(t) for t in data["tool_names"]]
    if scene is not None and tuple(tools) != scene["tools"]:
        out.append(f"contact.npz: tool_names {tools} must be {list(scene['tools'])}")
    if s is not None and isinstance(s.get("instants"), list) and names != s["instants"]:
        out.append(f"contact.npz: instant_names {names} differ from summary instants {s['instants']}")
    per = {"x": ((n_nodes, 2), "float64"), "eqps": ((n_el,), "float64"), "rn": ((m,), "float64"),
           "rt": ((m,), "float64"), "normal": ((m, 2), "float64"), "gap": ((m,), "float64"),
           "mu": ((m,), "float64"), "status": ((m,), "int8"), "tool_offset": ((n_tools, 2), "float64")}
    for name in names:
        complete = True
        for key, (shape, dtype) in per.items():
            full = f"{name}__{key}"
            if full not in data:
                out.append(f"contact.npz: missing {full!r}")
                complete = False
            elif data[full].dtype != np.dtype(dtype) or data[full].shape != shape:
                out.append(f"contact.npz: {full!r} is {data[full].dtype} {data[full].shape}, expected "
                           f"{dtype} {shape}")
                complete = False
            elif dtype == "float64" and not np.all(np.isfinite(data[full])):
                out.append(f"contact.npz: {full!r} has non-finite values")
                complete = False
        if complete and ok:
            _check_instant(data, name, names.index(name), s, cols, scene, tools, out)


def _check_instant(data, name, i, s, cols, scene, tools, out) -> None:
    rn, rt, mu = data[f"{name}__rn"], data[f"{name}__rt"], data[f"{name}__mu"]
    normal, gap, status = data[f"{name}__normal"], data[f"{name}__gap"], data[f"{name}__status"]
    where = f"contact.npz: instant {name!r}"
    if np.any(rn < -1e-9):
        out.append(f"{where}: rn < 0")
    if np.any(mu < 0):
        out.append(f"{where}: mu < 0")
    if np.any(gap > 1e30):
        out.append(f"{where}: gap above 1e30")
    length = np.linalg.norm(normal, axis=1)
    if np.any((np.abs(length - 1.0) > 1e-9) & (length != 0.0)):
        out.append(f"{where}: normal is neither a unit vector nor (0, 0)")
    if np.any((status < 0) | (status > 2)):
        out.append(f"{where}: status outside {{0, 1, 2}}")
    closed = rn > 1e-9
    expected = np.where(closed, np.where(np.abs(rt) < (1.0 - 1e-6) * mu * rn, 1, 2), 0)
    wrong = np.flatnonzero(expected != status)
    if wrong.size:
        p = int(wrong[0])
        out.append(f"{where}: status disagrees with rn, rt, mu (benchmarks spec section 0) at "
                   f"{wrong.size} pairs, e.g. pair {p}: status {int(status[p])}, rn {rn[p]:.6g}, "
                   f"rt {rt[p]:.6g}, mu {mu[p]:.6g}")
    if cols is None:
        return
    n = len(cols["step"])
    step = int(data["instant_steps"][i])
    if not 0 <= step < n:
        out.append(f"{where}: step {step} outside the history (0..{n - 1})")
        return
    if not _close(float(data["instant_drawing_displacement"][i]), cols["drawing_displacement"][step]):
        out.append(f"{where}: instant_drawing_displacement differs from history.csv at step {step}")
    n_active, n_slip = int(np.sum(status > 0)), int(np.sum(status == 2))
    if n_active != cols["n_active"][step] or n_slip != cols["n_slip"][step]:
        out.append(f"{where}: {n_active} active / {n_slip} slip pairs, history.csv step {step} has "
                   f"{cols['n_active'][step]} / {cols['n_slip'][step]}")
    if scene is not None and scene["clamp"][0] in tools:
        k = tools.index(scene["clamp"][0])
        e_q = np.asarray(scene["clamp"][1])
        t = np.stack([-normal[:, 1], normal[:, 0]], axis=1)
        f = rn[:, None] * normal + rt[:, None] * t
        proj = (f @ e_q)[data["pair_tool"] == k]
        total, expected_f = float(np.sum(proj)), cols["clamping_force"][step]
        scale = max(abs(expected_f), float(np.sum(np.abs(proj))))
        if abs(total - expected_f) > _RTOL_NPZ * scale + 1e-9:
            out.append(f"{where}: clamping force from the pairs {total:.9g} N/mm, history.csv step {step} "
                       f"has {expected_f:.9g}")
    # Instant rules that are plain functions of the history.
    phases = cols["phase"]
    fallback = s.get("instants_fallback", []) if s is not None else []
    if name == "final" and step != n - 1:
        out.append(f"{where}: 'final' must be the last step {n - 1}, got {step}")
    if name in fallback and step != n - 1:
        out.append(f"{where}: a fallback instant must be at the last step {n - 1}")
    if scene is not None and name in _END_OF:
        k = scene["phases"].index(_END_OF[name]) + 1
        if phases[step] != _END_OF[name] or abs(cols["time"][step] - k) > _TIME_TOL:
            out.append(f"{where}: must be the end of phase {_END_OF[name]!r} (time {k}), got step {step}")
    key = (s.get("scene") if s is not None else None, name)
    if key in _CLOSEST:
        draw = [j for j, p in enumerate(phases) if p == "draw"]
        best = min(draw, key=lambda j: abs(cols["drawing_displacement"][j] - _CLOSEST[key]), default=None)
        if best is not None and abs(cols["drawing_displacement"][step] - _CLOSEST[key]) > \
                abs(cols["drawing_displacement"][best] - _CLOSEST[key]) + _STEADY_TOL:
            out.append(f"{where}: not the draw step with drawing displacement closest to {_CLOSEST[key]} mm")


# ---- entry point ----------------------------------------------------------------------------------

def check_run_dir(path) -> list[str]:
    """Check the run directory ``path`` against outputs spec section 6.

    Returns:
        the violations, one line each ("<file>: <rule broken>"); empty when the directory conforms.
    """
    path = os.fspath(path)
    out: list[str] = []
    if not os.path.isdir(path):
        return [f"{path}: not a directory"]
    _check_files(path, out)
    summary = _read_summary(path, out)
    scene = _scene(summary.get("scene")) if summary is not None else None
    cols = _read_history(path, scene, out)
    if summary is not None:
        _check_summary(summary, cols, out)
    _check_contact(path, summary, cols, out)
    return out


def main(argv=None) -> int:
    """``python -m jaxfric.contract DIR ...``: print the violations; exit 1 if there are any."""
    paths = sys.argv[1:] if argv is None else list(argv)
    bad = 0
    for path in paths:
        problems = check_run_dir(path)
        bad += bool(problems)
        print(f"{path}: {'OK' if not problems else f'{len(problems)} violation(s)'}")
        for p in problems:
            print(f"  {p}")
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
