"""The run-directory checker (:mod:`jaxfric.io.contract`), section 3: ``summary.json``."""

from __future__ import annotations

import datetime
import json
import math
import os
from collections.abc import Callable
from typing import Any

from .contract_history import steady
from .contract_spec import (
    ALGORITHMS,
    TAG,
    TIME_TOL,
    close,
    is_int,
    is_number,
    scene_of,
)

__all__ = ["read_summary", "check_summary"]

# ---- 3. summary.json ------------------------------------------------------------------------------

def _reject_constant(name):
    raise ValueError(f"non-finite number {name}")


def read_summary(path: str, out: list) -> dict | None:
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
    if not (is_number(rel) and math.isfinite(rel) and rel >= 0):
        return ["summary.json: error_estimate relative must be a finite number >= 0"]
    if is_number(get(est["quantity"])) and not close(est["value"], get(est["quantity"])):
        return [f"summary.json: error_estimate value != {est['quantity']}"]
    return []


def _type_ok(value, kind: str) -> bool:
    if kind.endswith("|null"):
        return value is None or _type_ok(value, kind[:-5])
    return {
        "int": lambda v: is_int(v),
        "float": lambda v: is_number(v),
        "str": lambda v: isinstance(v, str),
        "bool": lambda v: isinstance(v, bool),
        "object": lambda v: isinstance(v, dict),
        "int2": lambda v: isinstance(v, list) and len(v) == 2 and all(is_int(x) for x in v),
        "float2": lambda v: isinstance(v, list) and len(v) == 2 and all(is_number(x) for x in v),
        "strlist": lambda v: isinstance(v, list) and all(isinstance(x, str) for x in v),
    }[kind](value)


def check_summary(s: dict, cols: dict | None, out: list) -> None:
    for key, kind in _SUMMARY_TYPES.items():
        if key not in s:
            out.append(f"summary.json: missing key {key!r}")
        elif not _type_ok(s[key], kind):
            out.append(f"summary.json: key {key!r} must be {kind}, got {s[key]!r:.60}")
    get: Callable[[str], Any] = s.get  # the value of a key, of any JSON type, or None
    if get("schema_version") != 1:
        out.append("summary.json: schema_version must be 1")
    scene = scene_of(get("scene"))
    if scene is None:
        out.append(f"summary.json: unknown scene {get('scene')!r}")
    elif get("variant") not in scene["variants"]:
        out.append(f"summary.json: unknown variant {get('variant')!r} for scene {get('scene')!r}")
    if get("algorithm") not in ALGORITHMS:
        out.append(f"summary.json: unknown algorithm {get('algorithm')!r}")
    if isinstance(get("tag"), str) and not TAG.match(get("tag")):
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
    if is_number(get("compile_s")) and get("compile_s") < 0:
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
        if not is_number(value):
            continue
        if (value != expected) if exact else not close(value, expected):
            out.append(f"summary.json: {key} = {value!r} but history.csv gives {expected!r}")
    if scene is not None:
        done = abs(cols["time"][-1] - len(scene["phases"])) <= TIME_TOL
        if isinstance(get("converged"), bool) and get("converged") != done:
            out.append(f"summary.json: converged = {get('converged')} but the last row's time is "
                       f"{cols['time'][-1]!r} of {len(scene['phases'])} phases")
    if get("converged") is False and not get("message"):
        out.append("summary.json: message must give the reason when converged is false")
    if _type_ok(get("steady_window"), "float2") and _type_ok(get("steady_drawing_force"), "float|null"):
        expected = steady(cols, get("steady_window"))
        value = get("steady_drawing_force")
        if (expected is None) != (value is None) or (value is not None and not close(value, expected)):
            out.append(f"summary.json: steady_drawing_force = {value!r}, recomputed from history.csv "
                       f"and steady_window: {expected!r}")
    if get("algorithm") == "auglag":
        if "n_aug" not in cols:
            out.append("history.csv: column 'n_aug' is required for auglag")
        elif is_number(get("mean_augmentations")) and n > 1 and \
                not close(get("mean_augmentations"), sum(cols["n_aug"]) / (n - 1)):
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
        if s.get("algorithm") == "auglag" and not is_number(contact["target_gap"]):
            out.append("summary.json: parameters.contact.target_gap must be a number for auglag")
    mesh = p.get("mesh")
    if isinstance(mesh, dict) and isinstance(s.get("mesh"), list) and \
            [mesh.get("nx"), mesh.get("ny")] != s["mesh"]:
        out.append(f"summary.json: mesh {s['mesh']} differs from parameters.mesh {mesh}")
