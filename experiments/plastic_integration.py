"""The step error of the Nine test with the radial return and with the midpoint rule
(``--set plastic_integration=radial|midpoint``, :class:`jaxfric.fem.material.J2Material`).

    python experiments/plastic_integration.py [--root DIR] [--only CASE ...]

Each case is the Nine at its defaults (300 x 3, ``ans``, the entry channel, exact contact) drawn 36 mm,
with the increments ``dU`` = ``dq_clamp`` of :data:`INCREMENTS` (the nominal 0.1 mm, then halved three
times), for each variant and integration: a run directory under ``--root`` (default
``runs/plastic_integration``; kept, so a second call reads it back, and a run directory of
``jaxfric run nine --variant V --set U_draw=36 --set dU=D --set dq_clamp=D --set plastic_integration=I``
may be put there as ``V_I_D``). Per variant and integration, the step-converged force is Richardson's
limit of the three finest runs with their observed ratio q of successive changes
(``error_estimates.richardson``); each run's step error is taken against the midpoint rule's limit, and
the two limits' difference is in the table too (both rules tend to the same force). Writes
``experiments/results/plastic_integration.csv`` and ``.png`` (step error against Newton iterations).
"""

from __future__ import annotations

import argparse
import os
import sys

from benchutil import run_or_read, write_rows
from error_estimates import richardson
from jaxfric import scenes
from jaxfric.fem.material import INTEGRATIONS

HERE = os.path.dirname(os.path.abspath(__file__))
VARIANTS = ("mu000", "mu017")
INCREMENTS = (0.1, 0.05, 0.025, 0.0125)   # mm
CASES = {f"{v}_{i}_{d:g}": (v, i, d) for v in VARIANTS for i in INTEGRATIONS for d in INCREMENTS}


def run_one(name: str, root: str) -> dict:
    """The figures of case ``name``, from its run directory under ``root`` (run first if absent; a failed run
    stops the study, naming its directory)."""
    variant, integration, increment = CASES[name]
    out = os.path.join(root, name)
    overrides = {"U_draw": 36.0, "dU": increment, "dq_clamp": increment, "plastic_integration": integration}
    s = run_or_read(out, lambda: scenes.make("nine", variant, "lcp_ssn", overrides), "plastic_integration",
                    f"{name}: running")
    if not s["converged"] or s["steady_drawing_force"] is None:
        raise SystemExit(f"{name}: the run in {out} did not finish ({s['message']})")
    return {"case": name, "variant": variant, "integration": integration, "increment": increment,
            "steps": s["n_steps"], "newton_iterations": s["newton_iters_total"], "cutbacks": s["n_cutbacks"],
            "steady_force": s["steady_drawing_force"]}


def with_errors(rows: list[dict]) -> list[dict]:
    """``rows`` with each run's step error (% of the force) against its variant's limit by the midpoint
    rule, and per variant and integration the limit and the observed ratio q of its three finest runs."""
    out = []
    for variant in VARIANTS:
        limits = {}
        for integration in INTEGRATIONS:
            ladder = sorted((r for r in rows if (r["variant"], r["integration"]) == (variant, integration)),
                            key=lambda r: -r["increment"])
            if len(ladder) == len(INCREMENTS):
                limits[integration] = richardson(*(r["steady_force"] for r in ladder[1:]))
        if "midpoint" not in limits:
            continue
        reference = limits["midpoint"][0]
        for r in rows:
            if r["variant"] == variant:
                limit, q = limits.get(r["integration"], (float("nan"), float("nan")))
                out.append({**r, "limit": limit, "q": q, "reference": reference,
                            "step_error_pct": 100.0 * (r["steady_force"] / reference - 1.0)})
    return out


def plot(rows: list[dict], path: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7.5, 5.0), constrained_layout=True)
    styles = {("mu000", "radial"): ("tab:blue", "o--"), ("mu000", "midpoint"): ("tab:blue", "s-"),
              ("mu017", "radial"): ("tab:red", "o--"), ("mu017", "midpoint"): ("tab:red", "s-")}
    for (variant, integration), (colour, style) in styles.items():
        own = sorted((r for r in rows if (r["variant"], r["integration"]) == (variant, integration)),
                     key=lambda r: r["newton_iterations"])
        if own:
            ax.loglog([r["newton_iterations"] for r in own], [abs(r["step_error_pct"]) for r in own], style,
                      color=colour, label=f"{variant}, {integration}")
    ax.set_xlabel("Newton iterations (Nine 300 x 3, drawn 36 mm)")
    ax.set_ylabel("|step error| of the steady drawing force (%)")
    ax.set_title("increments 0.1, 0.05, 0.025, 0.0125 mm")
    ax.grid(alpha=0.3, which="both")
    ax.legend()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--root", default=os.path.join("runs", "plastic_integration"))
    p.add_argument("--only", nargs="*", choices=sorted(CASES), help="run these cases only")
    a = p.parse_args(argv)
    rows = with_errors([run_one(n, a.root) for n in (a.only or CASES)])
    for r in rows:
        print(f"{r['case']:<22} {r['steps']:5d} steps {r['newton_iterations']:6d} its {r['cutbacks']:2d} cuts "
              f"F {r['steady_force']:.4f} error {r['step_error_pct']:+.3f} % (limit {r['limit']:.4f}, q {r['q']:.2f})")
    if not a.only:
        write_rows(os.path.join(HERE, "results", "plastic_integration.csv"), rows)
        plot(rows, os.path.join(HERE, "results", "plastic_integration.png"))
    return 0


if __name__ == "__main__":
    sys.exit(main())
