"""Independent checker of a run directory against the output contract (outputs spec section 6).

:func:`check_run_dir` reads only the files (no jaxfric run objects) and returns the list of
violations, each a one-line string naming the file and the rule; an empty list means the directory
satisfies the contract. The scene metadata it needs (identifiers, phases, instants, tools, clamping
tool and its closing direction, default steady windows) is restated here from the benchmarks spec on
purpose, so that the writer (:mod:`jaxfric.io.output`) is checked against the spec and not against itself.

Run as ``python -m jaxfric.io.contract DIR [DIR ...]``.
"""

from __future__ import annotations

import os
import struct
import sys

from .contract_contact import check_contact
from .contract_history import read_history
from .contract_spec import (
    FILES,
    PNG_SIGNATURE,
    SCENES,
    scene_of,
)
from .contract_summary import check_summary, read_summary

__all__ = ["check_run_dir", "FILES", "SCENES"]


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
            if head[:8] != PNG_SIGNATURE or head[12:16] != b"IHDR":
                out.append(f"{name}: not a PNG (bad signature or no IHDR header)")
                continue
            width, height = struct.unpack(">II", head[16:24])
            if width < 800 or height < 500:
                out.append(f"{name}: {width} x {height} px, at least 800 x 500 required")




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
    summary = read_summary(path, out)
    scene = scene_of(summary.get("scene")) if summary is not None else None
    cols = read_history(path, scene, out)
    if summary is not None:
        check_summary(summary, cols, out)
    check_contact(path, summary, cols, out)
    return out


def main(argv=None) -> int:
    """``python -m jaxfric.io.contract DIR ...``: print the violations; exit 1 if there are any."""
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
