"""The identification's compiled curve for one parameter, as a JVP or as ``jax.jacfwd``:
``python experiments/bench_curve_program.py [--mesh 100x2] [--stroke 3] [--param mu] [--repeats 1]
[--forms jvp,jacfwd] [--code DIR ...]``.

The curve (:mod:`jaxfric.identification.fit_curve`) is the replay of a frozen step sequence with its
Jacobian by forward mode through the whole loading path. ``jax.jacfwd`` is a ``vmap`` of the JVP, which
batches every loop of the path for the tangents, even a single one; :func:`~jaxfric.identification.fit_curve.
forward_jacobian` calls the JVP itself for one parameter. Each form is compiled in a new process with
``JAXFRIC_CACHE_DIR=off`` and the command lines' XLA flags (:func:`jaxfric.io.xla_flags.use_fast_compilation`),
as ``jaxfric fit`` compiles it: the Nine ``mu017`` at the fit's start value mu = 0.12, the windows of 1 mm
of ``jaxfric fit --window 1``, the step sequence of an adaptive run. Per form: the program's size in
StableHLO lines, JAX's tracing and lowering, XLA's compilation, one replay (the second call, compiled), and
the Jacobian, which both forms must give alike (``max_rel_diff``). ``--code DIR ...``: the package from
each checkout in turn (first on ``PYTHONPATH``; default this one), so that two versions are compared in
one sitting (``package`` column). Writes ``experiments/results/bench_curve_program.csv``.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time

from benchutil import write_rows

FORMS = ("jvp", "jacfwd")
HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
OUT = os.path.join(HERE, "results", "bench_curve_program.csv")


def measure(form: str, mesh: str, stroke: float, param: str) -> dict:
    """One form's figures, in this process."""
    import jax
    import jax.numpy as jnp
    import numpy as np

    from jaxfric.identification.fit_curve import curve_function, forward_jacobian, replay_options
    from jaxfric.identification.params import adaptive_run, parameterize, plan_steps

    par = parameterize("nine", [param], variant="mu017", algorithm="lcp_ssn",
                       overrides={"mesh": mesh, "U_draw": stroke, "mu": 0.12})
    plan = adaptive_run(par, par.p0).history
    steps = plan_steps(par, plan)
    newton = replay_options(par)
    edges = np.arange(0.0, stroke + 1e-9, 1.0)
    curve = curve_function(par, 0.5 * (edges[1:] + edges[:-1]), edges, newton)
    fn = jax.jit(forward_jacobian(curve, 1) if form == "jvp" else jax.jacfwd(curve, has_aux=True))
    p = jnp.asarray(par.p0)
    t0 = time.perf_counter()
    traced = fn.trace(p, steps)
    t1 = time.perf_counter()
    lowered = traced.lower()
    t2 = time.perf_counter()
    compiled = lowered.compile()
    t3 = time.perf_counter()
    jax.block_until_ready(compiled(p, steps))
    t4 = time.perf_counter()
    jac, (obs, _, code, _) = jax.block_until_ready(compiled(p, steps))
    t5 = time.perf_counter()
    return {"form": form, "mesh": mesh, "stroke_mm": stroke, "param": param, "steps": len(plan["time"]) - 1,
            "hlo_lines": lowered.as_text().count("\n"), "trace_s": round(t1 - t0, 2),
            "lower_s": round(t2 - t1, 2), "xla_s": round(t3 - t2, 2), "first_call_s": round(t4 - t3, 2),
            "replay_s": round(t5 - t4, 2), "code": int(code),
            "jacobian": [float(v) for v in np.asarray(jac).ravel()]}


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--mesh", default="100x2")
    ap.add_argument("--stroke", type=float, default=3.0, help="U_draw (mm)")
    ap.add_argument("--param", default="mu")
    ap.add_argument("--repeats", type=int, default=1, help="processes per form, taken in turns")
    ap.add_argument("--forms", default=",".join(FORMS), help="comma list of jvp, jacfwd")
    ap.add_argument("--code", nargs="+", default=[ROOT], help="package checkouts to compare (default: this one)")
    ap.add_argument("--out", default=OUT)
    ap.add_argument("--form", choices=FORMS, help=argparse.SUPPRESS)   # a child's one form
    args = ap.parse_args(argv)
    if args.form:
        print(json.dumps(measure(args.form, args.mesh, args.stroke, args.param)))
        return
    from jaxfric.io.xla_flags import use_fast_compilation

    env = dict(os.environ, JAXFRIC_CACHE_DIR="off")
    use_fast_compilation(env)
    rows = []
    for _ in range(args.repeats):
        for code in args.code:
            for form in args.forms.split(","):
                out = subprocess.run([sys.executable, os.path.abspath(__file__), "--form", form, "--mesh", args.mesh,
                                      "--stroke", str(args.stroke), "--param", args.param],
                                     env={**env, "PYTHONPATH": os.path.abspath(code)}, cwd=code, check=True, text=True,
                                     capture_output=True).stdout
                rows.append({"package": os.path.abspath(code), **json.loads(out.strip().splitlines()[-1])})
                print({k: v for k, v in rows[-1].items() if k != "jacobian"}, flush=True)
    ref = rows[0]["jacobian"]
    scale = max(abs(v) for v in ref)
    for row in rows:
        row["max_rel_diff"] = f"{max(abs(a - b) for a, b in zip(row.pop('jacobian'), ref)) / scale:.2e}"
    write_rows(args.out, rows)
    print("wrote", args.out)


if __name__ == "__main__":
    main()
