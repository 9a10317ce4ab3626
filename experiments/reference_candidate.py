"""One candidate run for an accuracy test's reference (issue 5, error against run time).

    python experiments/reference_candidate.py TEST --mesh NXxNY [--step F] --root DIR [--chunk N] [--progress]

Runs :func:`jaxfric.identification.accuracy.reference_overrides` of ``TEST`` (a name of
``jaxfric.identification.accuracy.TESTS``: its reference algorithm, base overrides and target gap) on ``--mesh`` with
``--step`` times the nominal increments, into ``DIR/<test's run directory>/ref_<algorithm>_<mesh>_x<step>/`` (the run
directory of
:func:`jaxfric.io.batch.run_case`, no figures), and prints one line with its steps, iterations, times and
forces. Used to choose a reference's mesh (a ladder of meshes, docs/results.md); a run's directory can then
be copied to the label the test gives its reference or a check (:func:`jaxfric.identification.accuracy.cases`), whose
overrides are the same. ``experiments/device_reference.sh`` runs a ladder of them side by side on a lent
GPU.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import sys

from jaxfric.fem.assembly import element_chunk
from jaxfric.identification import accuracy
from jaxfric.io.batch import run_case
from jaxfric.scenes import parse_mesh


def label(test: accuracy.Test, mesh: tuple, step: float) -> str:
    return f"ref_{test.ref_algorithm}_{mesh[0]}x{mesh[1]}_x{step:g}"


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("test", help="accuracy test name, e.g. nine_mu017")
    p.add_argument("--mesh", required=True, help="NXxNY")
    p.add_argument("--step", type=float, default=None, help="factor on the nominal increments "
                   "(default: the test's ref_step)")
    p.add_argument("--root", required=True, help="directory of the runs")
    p.add_argument("--chunk", type=int, default=None, help="elements per chunk of the element loops "
                   "(default: the package's)")
    p.add_argument("--progress", action="store_true", help="progress bar on stderr")
    a = p.parse_args(argv)
    tests = {t.name: t for t in accuracy.TESTS}
    if a.test not in tests:
        p.error(f"unknown test {a.test!r}; choose from {', '.join(tests)}")
    test = tests[a.test]
    mesh = parse_mesh(a.mesh)
    step = test.ref_step if a.step is None else a.step
    overrides = accuracy.reference_overrides(test, mesh, step)
    out = os.path.join(a.root, test.run_dir, label(test, mesh, step))
    with element_chunk(a.chunk) if a.chunk else contextlib.nullcontext():
        c = run_case(out, test.scene, test.variant, test.ref_algorithm, overrides, progress=a.progress,
                     log=lambda m: print(m, file=sys.stderr, flush=True))
    s = c["summary"]
    keys = ("converged", "n_steps", "newton_iters_total", "n_cutbacks", "compile_s", "wall_s",
            "steady_drawing_force", "peak_drawing_force", "final_clamping_force", "message")
    print(json.dumps({"test": test.name, "mesh": a.mesh, "step": step, **{k: s.get(k) for k in keys}}), flush=True)
    return 0 if s.get("converged") else 1


if __name__ == "__main__":
    sys.exit(main())
