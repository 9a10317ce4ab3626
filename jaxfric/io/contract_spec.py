"""The outputs spec's vocabulary as the run-directory checker states it (:mod:`jaxfric.io.contract`): files,
required columns, scenes with their phases, instants and tools, tolerances, and the checks' number tests.
Restated from the benchmarks and outputs specs on purpose, not imported from the code that writes runs; only
the algorithm identifiers come from the package (:data:`jaxfric.contact.formulations.ALGORITHMS`)."""

from __future__ import annotations

import math
import re
from typing import Any

from ..contact.formulations import ALGORITHMS

__all__ = ["FILES", "REQUIRED", "SCENES", "ALGORITHMS", "close", "is_number", "is_int", "scene_of"]

FILES = ("history.csv", "summary.json", "contact.npz", "forces.png", "contact.png", "mesh.png")
REQUIRED = ("step", "phase", "time", "drawing_displacement", "drawing_force", "clamping_force",
            "tool_position", "max_penetration", "n_active", "n_slip", "newton_iters", "wall_s")
INT_REQUIRED = ("step", "n_active", "n_slip", "newton_iters")
INT_EXTRAS = ("cutbacks", "n_aug", "lcp_pivots", "ssn_iters", "ssn_fallbacks")

# Per scene: variants, phases, instants, tools, (clamping tool, e_q), default steady window (mm);
# extra_tools: tools a scene's config may add after the spec's (the Nine's entry guide, its ``entry_guide``).
SCENES: dict[str, dict[str, Any]] = {
    "flat_die": dict(variants=("const_force", "const_position"), phases=("clamp", "draw"),
                     instants=("clamped", "intermediate", "sliding", "final"), tools=("die",),
                     clamp=("die", (0.0, -1.0)), window=(0.02, 0.03)),
    "bead": dict(variants=tuple(f"th{t}_mu{m}" for m in ("000", "017") for t in ("045", "090", "135")),
                 phases=("clamp", "wind", "draw"), instants=("clamped", "folded", "drawing", "final"),
                 tools=("die_up", "die_lo", "roller"), clamp=("die_up", (0.0, -1.0)), window=(4.0, 8.0)),
    "nine": dict(variants=("mu000", "mu017"), phases=("clamp", "draw"),
                 instants=("clamped", "steady", "final"), tools=("A", "B", "C", "D", "E"),
                 extra_tools=("guide_top", "guide_bottom"), clamp=("B", (0.0, -1.0)), window=(20.0, 35.0)),
    "blankholder": dict(variants=tuple(f"shape{k}" for k in range(1, 10)), phases=("close", "lock", "draw"),
                        instants=("closed", "locked", "drawing", "final"), tools=("upper", "lower"),
                        clamp=("lower", (0.0, 1.0)), window=(35.0, 55.0)),
}
# Instants at the end of a phase, and "closest to" instants (phase, drawing displacement in mm).
END_OF = {"clamped": "clamp", "folded": "wind", "closed": "close", "locked": "lock"}
CLOSEST = {("bead", "drawing"): 4.0, ("nine", "steady"): 27.5, ("blankholder", "drawing"): 27.5}

TAG = re.compile(r"[A-Za-z0-9][A-Za-z0-9._+-]*\Z")
NAME = re.compile(r"[a-z][a-z0-9_]*\Z")
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
RTOL, ATOL = 1e-9, 1e-12       # summary vs history (outputs spec section 3)
RTOL_NPZ = 1e-6                 # contact.npz vs history (outputs spec section 4)
STEADY_TOL = 1e-9               # mm (benchmarks spec section 6)
TIME_TOL = 1e-9


def close(a, b, rtol=RTOL, atol=ATOL) -> bool:
    return abs(a - b) <= atol + rtol * max(abs(a), abs(b))


def is_number(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def is_int(v) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)

def scene_of(name: Any) -> dict[str, Any] | None:
    """The metadata of the scene ``name`` (any value read from summary.json); None if it names no scene."""
    return SCENES.get(name)
