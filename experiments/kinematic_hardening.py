"""The Bauschinger effect in the Nine test and the bead: ``python experiments/kinematic_hardening.py``.

    python experiments/kinematic_hardening.py [--root DIR] [--only CASE ...] [--table]

Each case is one scene variant run twice with exact contact (``lcp_ssn``), at the spec mesh and the
nominal increments: with the spec's isotropic hardening, and with one Armstrong-Frederick back stress
(``--set C_kin=2000 --set gamma_kin=20``, :mod:`jaxfric.fem.kinematic`) whose isotropic radius is the
power law less the back stress's saturation, so that both laws share the spec's monotonic hardening curve
and differ only after a reversal. The Nine is drawn 36 mm (its steady window, U in [20, 35] mm, ends
before the tail reaches the bead); the bead takes its whole schedule. Run directories go under
``--root`` (default ``runs/kinematic_hardening``; kept: a second call reads them back).

C = 2000 MPa, gamma = 20 are chosen, not a published fit: the back stress saturates at C / gamma = 100 MPa
(about a third of the Nine steel's flow stress at 10 % plastic strain) within about 15 % of plastic
strain, so a strip reversed after the Nine's first bend yields again at roughly half its forward flow
stress, and the isotropic radius stays non-decreasing (its slope sigma_y n A (1 + A p)^(n - 1) exceeds
C exp(-gamma p) for every p >= 0 with the Nine's steel).

Per case the table (``experiments/results/kinematic_hardening.csv``) gives the steady drawing force
(the Nine) or the final drawing force (the bead) under each law, their ratio, the largest equivalent
plastic strain and the Newton iterations; the figure (``.png``) the drawing force against the drawing
displacement under both laws.
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import sys

import numpy as np

import jaxfric as jf
from benchutil import write_rows
from jaxfric import scenes
from jaxfric.io import output

HERE = os.path.dirname(os.path.abspath(__file__))
KINEMATIC = {"C_kin": (2000.0,), "gamma_kin": (20.0,)}
SETTINGS = {"nine": {"U_draw": 36.0}, "bead": {}}
CASES = {"nine_mu000": ("nine", "mu000"), "nine_mu017": ("nine", "mu017"),
         "bead_th090_mu017": ("bead", "th090_mu017")}
LAWS = ("isotropic", "kinematic")


def _history(out: str) -> dict:
    """The numeric columns of a run's history, as arrays."""
    with open(os.path.join(out, "history.csv")) as fh:
        rows = list(csv.DictReader(fh))
    return {k: np.array([float(r[k]) for r in rows]) for k in rows[0] if k not in ("phase", "phase_name")}


def run_one(case: str, law: str, root: str) -> tuple[dict, dict]:
    """Run (or read back) ``case`` under ``law``: its summary and history."""
    name, variant = CASES[case]
    out = os.path.join(root, f"{case}_{law}")
    if not os.path.exists(os.path.join(out, "summary.json")):
        overrides = dict(SETTINGS[name], **(KINEMATIC if law == "kinematic" else {}))
        scene = scenes.make(name, variant, "lcp_ssn", overrides)
        print(f"{case} {law}: running", file=sys.stderr, flush=True)
        result = jf.run(scene.model, newton=scene.newton, control=scene.control, observe=scene.observe,
                        snapshot=scene.snapshot, progress=False, raise_on_failure=False)
        output.write_run(scene, result, out, tag="kinematic_hardening", figures=False)
    with open(os.path.join(out, "summary.json")) as fh:
        summary = json.load(fh)
    contact = np.load(os.path.join(out, "contact.npz"))
    eqps = max(float(np.max(contact[k])) for k in contact.files if k.endswith("__eqps"))
    return dict(summary, eqps_max=eqps), _history(out)


def row(case: str, runs: dict) -> dict:
    """The table row of ``case`` from its two runs (law -> (summary, history))."""
    def force(law):
        s, h = runs[law]
        steady = s.get("steady_drawing_force")
        return float(steady) if steady is not None else float(h["drawing_force"][-1])

    iso, kin = force("isotropic"), force("kinematic")
    out = {"case": case, "output": "steady" if CASES[case][0] == "nine" else "final",
           "force_isotropic": iso, "force_kinematic": kin, "ratio": kin / iso}
    for law in LAWS:
        s, _ = runs[law]
        out |= {f"eqps_max_{law}": s["eqps_max"], f"newton_{law}": s["newton_iters_total"],
                f"converged_{law}": s["converged"]}
    return out


def figure(histories: dict, path: str) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cases = sorted({c for c, _ in histories})
    fig, axes = plt.subplots(1, len(cases), figsize=(5.5 * len(cases), 4), constrained_layout=True, squeeze=False)
    for ax, case in zip(axes[0], cases, strict=True):
        for law, style in zip(LAWS, ("-", "--"), strict=True):
            h = histories[(case, law)]
            draw = h["drawing_force"] != 0.0
            key = "drawing_displacement" if "drawing_displacement" in h else "time"
            ax.plot(h[key][draw], h["drawing_force"][draw], style, lw=1.2, label=law)
        ax.set(title=case, xlabel="drawing displacement (mm)" if CASES[case][0] == "nine" else "pseudo-time",
               ylabel="drawing force (N/mm)")
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
            case, law = name.rsplit("_", 1)
            run_one(case, law, args.root)
        return 0
    rows, histories = [], {}
    for case in CASES:
        if args.table and not all(os.path.exists(os.path.join(args.root, f"{case}_{law}", "summary.json"))
                                  for law in LAWS):
            continue
        runs = {law: run_one(case, law, args.root) for law in LAWS}
        histories |= {(case, law): runs[law][1] for law in LAWS}
        rows.append(row(case, runs))
        print(rows[-1])
    if not rows:
        print("no case on disk", file=sys.stderr)
        return 1
    write_rows(os.path.join(HERE, "results", "kinematic_hardening.csv"), rows)
    figure(histories, os.path.join(HERE, "results", "kinematic_hardening.png"))
    return 0


if __name__ == "__main__":
    sys.exit(main())
