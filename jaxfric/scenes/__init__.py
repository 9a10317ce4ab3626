"""The four benchmark scenes (benchmarks spec sections 2 to 6) and their registry.

    >>> from jaxfric.scenes import make
    >>> scene = make("nine", "mu017", "penalty", {"mesh": "150x3", "U_draw": "40"})
    >>> result = jaxfric.run(scene.model, control=scene.control, observe=scene.observe,
    ...                      snapshot=scene.snapshot)

Each scene module defines a frozen config dataclass (fields = the spec's config keys, with units in
their metadata), ``VARIANTS`` (field overrides per variant), ``DEFAULT_VARIANT`` and
``build(config, algorithm, variant) -> Scene``. :func:`make` applies a variant, then user overrides
(typed values, or strings as given on a command line, converted by :func:`parse_override`).
"""

from __future__ import annotations

import dataclasses
import math
import types
import typing

from ..contact.formulations import ALGORITHMS
from ..fem.mesh import MAX_ELEMENTS
from . import bead, blankholder, flat_die, nine
from ._common import FrictionLawFields, check_steady_window
from .base import Scene

__all__ = ["SCENES", "ALGORITHMS", "Scene", "scene_names", "variants", "variant_values", "default_variant",
           "config_class", "config_fields", "make", "parse_override", "parse_mesh", "scaled_steps",
           "coarser_along", "finer_along", "finer_through"]

SCENES = {"flat_die": flat_die, "bead": bead, "nine": nine, "blankholder": blankholder}

_CONFIGS = {"flat_die": flat_die.FlatDieConfig, "bead": bead.BeadConfig, "nine": nine.NineConfig,
            "blankholder": blankholder.BlankholderConfig}


def _module(name: str):
    if not isinstance(name, str) or name not in SCENES:
        raise ValueError(f"unknown scene {name!r}; choose one of {', '.join(SCENES)}")
    return SCENES[name]


def scene_names() -> tuple:
    """Scene names in spec order."""
    return tuple(SCENES)


def variants(name: str) -> tuple:
    """Variant names of a scene, in spec order."""
    return tuple(_module(name).VARIANTS)


def variant_values(name: str, variant: str) -> dict:
    """The config field values that variant ``variant`` of scene ``name`` sets (the others keep their
    defaults)."""
    return dict(_module(name).VARIANTS[variant])


def default_variant(name: str) -> str:
    return _module(name).DEFAULT_VARIANT


def config_class(name: str) -> type:
    _module(name)
    return _CONFIGS[name]


def config_fields(name: str) -> list:
    """[(field, default, unit, doc), ...] of a scene's config, in declaration order, the friction-law
    fields every scene shares (``FrictionLawFields``) last."""
    shared = {f.name for f in dataclasses.fields(FrictionLawFields)}
    fields = sorted(dataclasses.fields(config_class(name)), key=lambda f: f.name in shared)
    return [(f.name, f.default, f.metadata.get("unit", ""), f.metadata.get("doc", "")) for f in fields]


def scaled_steps(name: str, config, factor: float) -> dict:
    """Config overrides that scale the nominal increments of ``config`` (a scene's config dataclass) by
    ``factor``: increments are multiplied by it, step counts divided by it (rounded up, at least 1), and
    where the increments follow the step error estimate (``step_error`` > 0) its target too, which
    scales a first-order step error as the increments do (the nominal increments alone hardly move such
    a run: docs/results.md, increments by the step error)."""
    if not (isinstance(factor, (int, float)) and math.isfinite(factor) and factor > 0):
        raise ValueError(f"field 'factor' must be a finite number > 0, got {factor!r}")
    out = {}
    for field in _module(name).STEP_FIELDS:
        value = getattr(config, field)
        out[field] = max(1, math.ceil(value / factor)) if isinstance(value, int) else value * factor
    if getattr(config, "step_error", 0.0) > 0:
        out["step_error"] = config.step_error * factor
    return out


def coarser_along(name: str, config) -> dict:
    """Config overrides for about half the elements along the strip, the same layers: ``nx`` halved
    (rounded down, at least 1), or, where ``nx`` is None and derived from ``element_length``
    (the blankholder), the element length doubled."""
    _module(name)
    if getattr(config, "nx", None) is None and hasattr(config, "element_length"):
        return {"element_length": 2.0 * config.element_length}
    return {"nx": max(1, config.nx // 2)}


def finer_along(name: str, config, factor: int = 2) -> dict:
    """Config overrides for ``factor`` times the elements along the strip, the same layers: ``nx``
    multiplied, or, where ``nx`` is None and derived from ``element_length`` (the blankholder), the element
    length divided by ``factor``."""
    _module(name)
    if getattr(config, "nx", None) is None and hasattr(config, "element_length"):
        return {"element_length": config.element_length / factor}
    return {"nx": factor * config.nx}


def finer_through(name: str, config, factor: int = 2) -> dict:
    """Config overrides for ``factor`` times the elements through the thickness, the same elements along."""
    _module(name)
    return {"ny": factor * config.ny}


def parse_mesh(text) -> tuple[int, int]:
    """"NXxNY" (e.g. "300x3") -> (nx, ny); a pair of integers is passed through."""
    if isinstance(text, (tuple, list)) and len(text) == 2:
        nx, ny = text
        if not all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in text):
            raise ValueError(f"field 'mesh' needs two finite integers, got {text!r}")
    else:
        parts = str(text).strip().lower().split("x")
        if len(parts) != 2:
            raise ValueError(f"field 'mesh' must read NXxNY (e.g. 300x3), got {text!r}")
        try:
            nx, ny = int(parts[0]), int(parts[1])
        except ValueError:
            raise ValueError(f"field 'mesh' must read NXxNY with integers (e.g. 300x3), got {text!r}") from None
    if int(nx) != nx or int(ny) != ny or not (1 <= nx <= MAX_ELEMENTS and 1 <= ny <= MAX_ELEMENTS):
        raise ValueError(f"field 'mesh' needs integers in [1, {MAX_ELEMENTS}], got {text!r}")
    if nx * ny > MAX_ELEMENTS:
        raise ValueError(f"field 'mesh' = {text!r} gives {int(nx) * int(ny):,} elements, more than {MAX_ELEMENTS:,}")
    return int(nx), int(ny)


def _field_type(name: str, field: str):
    hints = typing.get_type_hints(config_class(name))
    if field not in hints:
        known = ", ".join(f.name for f in dataclasses.fields(config_class(name)))
        raise ValueError(f"unknown config field {field!r} of scene '{name}'; known fields: {known}, mesh")
    hint = hints[field]
    args = typing.get_args(hint) if isinstance(hint, types.UnionType) or typing.get_origin(hint) is typing.Union else ()
    optional = type(None) in args
    base = next((a for a in args if a is not type(None)), hint) if args else hint
    return typing.get_origin(base) or base, optional


_BOOLEANS = {"true": True, "yes": True, "on": True, "1": True, "false": False, "no": False, "off": False,
             "0": False}


def parse_override(name: str, field: str, text: str):
    """Convert the string ``text`` to the type of config field ``field`` of scene ``name``.

    Floats, ints and strings as such; "none" for an optional field; tuples as comma-separated numbers
    ("20,35" or "(20, 35)"); ``mesh`` "NXxNY" as (nx, ny) (:func:`parse_mesh`). A bad value or an
    unknown field gives a one-line ValueError naming it.
    """
    if field == "mesh":
        _module(name)
        return parse_mesh(text)
    kind, optional = _field_type(name, field)
    raw = str(text).strip()
    if optional and raw.lower() in ("none", "null", ""):
        return None
    try:
        if kind is bool:
            return _BOOLEANS[raw.lower()]
        if kind is float:
            return float(raw)
        if kind is int:
            value = float(raw)
            if not math.isfinite(value) or value != int(value) or abs(value) > 2**31 - 1:
                raise ValueError
            return int(value)
        if kind is tuple:
            return tuple(float(v) for v in raw.strip("()[] ").split(","))
        return raw
    except (ValueError, KeyError):
        what = {float: "a number", int: "an integer (below 2**31)", tuple: "comma-separated numbers",
                bool: "true or false"}.get(kind, "a value")
        raise ValueError(f"config field '{field}' of scene '{name}' must be {what}, got {text!r}") from None


def _coerce(name: str, field: str, value):
    """A typed override: strings are parsed, ints widened to float for float fields, lists to tuples."""
    if isinstance(value, str):
        kind, _ = _field_type(name, field)
        return value if kind is str else parse_override(name, field, value)
    kind, optional = _field_type(name, field)
    if value is None:
        if not optional:
            raise ValueError(f"config field '{field}' of scene '{name}' cannot be None")
        return None
    if kind is bool and not isinstance(value, bool):
        raise ValueError(f"config field '{field}' of scene '{name}' must be True or False, got {value!r}")
    if kind is float and isinstance(value, int) and not isinstance(value, bool):
        return float(value)
    if kind is tuple and isinstance(value, list):
        return tuple(value)
    return value


def make(name: str, variant: str | None = None, algorithm: str = "penalty",
         overrides: dict | None = None) -> Scene:
    """Build scene ``name``: its variant's field values, then ``overrides`` (field -> value or string;
    ``mesh`` -> "NXxNY" or (nx, ny) sets nx and ny, checked by :func:`parse_mesh`), for ``algorithm``
    (one of :data:`ALGORITHMS`)."""
    module = _module(name)
    variant = module.DEFAULT_VARIANT if variant is None else variant
    if not isinstance(variant, str) or variant not in module.VARIANTS:
        raise ValueError(f"unknown variant {variant!r} of scene '{name}'; choose one of "
                         f"{', '.join(module.VARIANTS)}")
    values = dict(module.VARIANTS[variant])
    overrides = {} if overrides is None else overrides
    if not isinstance(overrides, dict):
        raise ValueError(f"field 'overrides' must be a dict of config field -> value, got {type(overrides).__name__}")
    if "mesh" in overrides and ({"nx", "ny"} & set(overrides)):
        raise ValueError("give the mesh either as 'mesh' (NXxNY) or as 'nx'/'ny', not both")
    for field, value in overrides.items():
        if field == "mesh":
            values["nx"], values["ny"] = parse_mesh(value)
        else:
            values[field] = _coerce(name, field, value)
    config = config_class(name)(**values)
    scene = module.build(config, algorithm, variant)
    if "steady_window" in overrides:
        check_steady_window(config, module.STROKE_FIELD)
    return scene
