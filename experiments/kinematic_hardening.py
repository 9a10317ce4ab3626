"""The Bauschinger effect in the Nine test and the bead: ``python experiments/kinematic_hardening.py``.

    python experiments/kinematic_hardening.py [--root DIR] [--only CASE ...] [--table]

Each case is one scene variant run with exact contact (``lcp_ssn``) at the spec mesh and the nominal
increments, under two pairs of laws; in each pair both laws share one monotonic hardening curve and
differ only after a reversal (:mod:`jaxfric.fem.kinematic`, ``keep_monotonic``), so the pair's ratio is
the Bauschinger effect alone:

- ``spec``: the spec's steel with isotropic hardening, and with one Armstrong-Frederick back stress
  (``--set C_kin=2000 --set gamma_kin=20``) taking its saturation out of the radius. C = 2000 MPa,
  gamma = 20 are chosen, not fitted: the back stress saturates at C / gamma = 100 MPa (a third of the
  steel's flow stress at 10 % plastic strain) within about 15 % of plastic strain, and the radius stays
  non-decreasing (its slope sigma_y n A (1 + A p)^(n - 1) exceeds C exp(-gamma p) at every p >= 0).
- ``s355``: a published fit, Hartloper et al.'s S355J2+N (``jaxfric.fem.kinematic.S355J2N``: two back
  stresses, E = 197.41 GPa, f_y = 338.8 MPa, nu = 0.3 assumed), and the isotropic law of its monotonic
  curve (the same Voce terms with the back stresses' saturation C_i / gamma_i added as Voce terms of rate
  gamma_i, and no back stress). The strip is then of that steel, about twice as strong as the spec's.

The Nine is drawn 36 mm (its steady window, U in [20, 35] mm, ends before the tail reaches the bead);
the bead takes its whole schedule. Run directories go under ``--root`` (default
``runs/kinematic_hardening``; kept: a second call reads them back).

Per case and pair the table (``experiments/results/kinematic_hardening.csv``) gives the steady drawing
force under each law, their ratio, the largest equivalent plastic strain and the Newton iterations; the
figure (``.png``) the drawing force against the drawing displacement under all four laws.
"""

from __future__ import annotations

import argparse
import os
import sys

import numpy as np

from benchutil import write_rows
from jaxfric.fem.kinematic import S355J2N
from jaxfric.io.batch import run_case

HERE = os.path.dirname(os.path.abspath(__file__))
_S355 = {"E": S355J2N["E"], "nu": 0.3, "sigma_y": S355J2N["sigma_y"], "A": 0.0, "n": 0.0,
         "Q_voce": S355J2N["Q"] + tuple(c / g for c, g in zip(S355J2N["C"], S355J2N["gamma"], strict=True)),
         "b_voce": S355J2N["b"] + S355J2N["gamma"]}
LAWS = {"isotropic": {}, "kinematic": {"C_kin": (2000.0,), "gamma_kin": (20.0,)},
        "s355_isotropic": _S355, "s355_kinematic": dict(_S355, C_kin=S355J2N["C"], gamma_kin=S355J2N["gamma"])}
PAIRS = {"spec": ("isotropic", "kinematic"), "s355": ("s355_isotropic", "s355_kinematic")}
SETTINGS = {"nine": {"U_draw": 36.0}, "bead": {}}
CASES = {"nine_mu000": ("nine", "mu000"), "nine_mu017": ("nine", "mu017"),
         "bead_th090_mu017": ("bead", "th090_mu017")}


def run_one(case: str, law: str, root: str) -> tuple[dict, dict]:
    """Run (or read back) ``case`` under ``law``: its summary (with the largest eqps) and history."""
    name, variant = CASES[case]
    done = run_case(os.path.join(root, f"{case}_{law}"), name, variant, "lcp_ssn", dict(SETTINGS[name], **LAWS[law]),
                    tag="kinematic_hardening", log=lambda line: print(line, file=sys.stderr, flush=True))
    eqps = max(float(np.max(v)) for k, v in done["contact"].items() if k.endswith("__eqps"))
    return dict(done["summary"], eqps_max=eqps), done["history"]


def row(case: str, pair: str, runs: dict) -> dict:
    """The table row of ``case`` under ``pair`` from its runs (law -> (summary, history))."""
    iso, kin = PAIRS[pair]

    def force(law):
        s, h = runs[law]
        steady = s.get("steady_drawing_force")
        return float(steady) if steady is not None else float(h["drawing_force"][-1])

    out = {"case": case, "pair": pair, "force_isotropic": force(iso), "force_kinematic": force(kin),
           "ratio": force(kin) / force(iso)}
    for name, law in (("isotropic", iso), ("kinematic", kin)):
        s, _ = runs[law]
        out |= {f"eqps_max_{name}": s["eqps_max"], f"newton_{name}": s["newton_iters_total"],
                f"converged_{name}": s["converged"]}
    return out


def figure(histories: dict, path: str) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cases = sorted({c for c, _ in histories})
    fig, axes = plt.subplots(1, len(cases), figsize=(5.5 * len(cases), 4), constrained_layout=True, squeeze=False)
    for ax, case in zip(axes[0], cases, strict=True):
        for law, style in zip(LAWS, ("-", "--", "-", "--"), strict=True):
            h = histories[(case, law)]
            ax.plot(h["drawing_displacement"], h["drawing_force"], style, lw=1.2, label=law)
        ax.set(title=case, xlabel="drawing displacement (mm)", ylabel="drawing force (N/mm)")
        ax.legend()
    fig.savefig(path, dpi=110)
    print(f"written {path}")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--root", default=os.path.join("runs", "kinematic_hardening"))
    p.add_argument("--only", nargs="+", choices=[f"{c}_{law}" for c in CASES for law in LAWS])
    p.add_argument("--table", action="store_true", help="only read back the runs on disk")
    args = p.parse_args(argv)
    if args.only:
        for name in args.only:
            case, law = next((c, law) for c in CASES for law in LAWS if name == f"{c}_{law}")
            run_one(case, law, args.root)
        return 0
    rows, histories = [], {}
    for case in CASES:
        if args.table and not all(os.path.exists(os.path.join(args.root, f"{case}_{law}", "summary.json"))
                                  for law in LAWS):
            continue
        runs = {law: run_one(case, law, args.root) for law in LAWS}
        histories |= {(case, law): runs[law][1] for law in LAWS}
        for pair in PAIRS:
            rows.append(row(case, pair, runs))
            print(rows[-1])
    if not rows:
        print("no case on disk", file=sys.stderr)
        return 1
    write_rows(os.path.join(HERE, "results", "kinematic_hardening.csv"), rows)
    figure(histories, os.path.join(HERE, "results", "kinematic_hardening.png"))
    return 0


if __name__ == "__main__":
    sys.exit(main())
