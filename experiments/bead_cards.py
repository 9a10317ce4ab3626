"""Bead cards of the blankholder's nine bead shapes: ``python experiments/bead_cards.py``.

    python experiments/bead_cards.py [--only shapeN ...] [--table] [--rewrite] [--kinematic] [--s355]

Per shape (spec Table 7, the paper's aluminium sheet, mu = 0.15, the spec mesh and the blankholder's element
(``anst``, 4 points per layer), ``lcp_ssn``): the card of
:func:`jaxfric.cards.bead_card` at 0.25, 0.5, 0.75 and 1 times the bead height (with the derivatives for
R, t and mu on shape3), written as ``experiments/results/bead_cards/<shape>/bead_card.{k,rad,csv,png,json}``,
and its consistency check: the full-depth bead (``lock_control=depth``) drawn the spec's whole 55 mm with
the spec's steady window [35, 55] mm, against the card's full-depth point (pulled 35, 46 or 58 mm for the
6, 9 and 12 mm beads, the last 10 mm its window: :func:`jaxfric.cards.bead.card_pull`), within that run's
error estimate, for the restraining force and for the normal force. ``--kinematic``: shape1's card again
with one Armstrong-Frederick back stress (``C_kin=2000, gamma_kin=20``, the same monotonic curve;
:mod:`jaxfric.fem.kinematic`), into ``bead_cards/shape1_kinematic``. ``--s355``: shape1's card with the
sheet of a published cyclic fit, Hartloper et al.'s S355J2+N with its two back stresses, and with the
isotropic law of the same monotonic curve (``experiments/kinematic_hardening.py``'s ``s355`` pair), into
``bead_cards/shape1_s355_kinematic`` and ``bead_cards/shape1_s355_isotropic``.

The table (``experiments/results/bead_cards.csv``) has, per shape, the full-depth forces, thinning and
plastic strain, the consistency run's force and error estimate (``bead_cards_derivatives.csv``: the
derivatives per penetration of the restraining force, its bending part, the normal force, the thinning
and the mean and largest plastic strain after the bead); the figure
(``experiments/results/bead_cards.png``) the restraining and normal forces of every shape against the
penetration as a fraction of its height. ``--only`` computes some shapes (to spread them over processes),
``--table`` only reads back what is on disk; ``--rewrite`` writes each card's files again from its
``bead_card.json`` (:func:`jaxfric.cards.formats.load_card`), with the current writers, without running it;
``--recheck LABEL ...`` runs those cards' consistency runs again.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys

import jax
import numpy as np

from benchutil import write_rows
from jaxfric.cards import bead_card, write_card
from jaxfric.cards.formats import load_card
from jaxfric.io.batch import run_case
from jaxfric.io.instants import steady_drawing_force, steady_rows
from kinematic_hardening import LAWS

HERE = os.path.dirname(os.path.abspath(__file__))
OUT = os.path.join(HERE, "results", "bead_cards")
SHAPES = tuple(f"shape{k}" for k in range(1, 10))
DERIVATIVES = {"shape3": ("R", "t", "mu")}
KINEMATIC = LAWS["kinematic"]
S355 = {"shape1_s355_isotropic": LAWS["s355_isotropic"], "shape1_s355_kinematic": LAWS["s355_kinematic"]}
LABELS = (*SHAPES, "shape1_kinematic", *S355)


def consistency(name: str, overrides: dict | None, out: str) -> dict:
    """The full-depth bead (``lock_control=depth``) drawn the spec's whole 55 mm (run into ``out``/
    full_depth_run, its summary kept): its steady drawing force with the run's error estimate, and its
    steady normal force (on the lower tool) with the estimate of the same components (contact, Newton
    tolerance, the force's own scatter over the window)."""
    log = lambda line: print(line, file=sys.stderr, flush=True)  # noqa: E731
    run_dir = os.path.join(out, "full_depth_run")
    shutil.rmtree(run_dir, ignore_errors=True)  # a kept run is its summary only, which cannot be read back
    done = run_case(run_dir, "blankholder", name, "lcp_ssn", {**(overrides or {}), "lock_control": "depth"},
                    tag="bead_cards", log=log)
    # The last run of a card (computed or rechecked): its programs and the card's are freed here. Each
    # compiled program holds memory mappings of its code until it is freed; a process that computes
    # several cards otherwise ends where the kernel's limit on mappings (vm.max_map_count, 65530 by
    # default) stops XLA's compiler ("LLVM compilation error: Cannot allocate memory").
    jax.clear_caches()
    s, h = done["summary"], done["history"]
    for f in os.listdir(run_dir):  # keep its summary only: the history is long and the card is the result
        if f != "summary.json":
            os.remove(os.path.join(run_dir, f))
    window = s.get("steady_window")
    estimate = s.get("error_estimate", {})
    check = {"steady_drawing_force": s.get("steady_drawing_force"), "converged": s["converged"],
             "error_estimate": estimate.get("absolute"), "steady_window": window, "message": s["message"]}
    values = {"phase": h["phase"], "drawing_displacement": h["drawing_displacement"]}
    normal = None if window is None else steady_drawing_force({**values, "drawing_force": h["clamping_force"]},
                                                                window)
    if normal is not None:
        rows = steady_rows(h["phase"], h["drawing_displacement"], window)
        scatter = float(np.std(np.asarray(h["clamping_force"])[rows])) / abs(normal)
        parts = estimate.get("components", {})
        relative = float(np.sqrt(parts.get("contact", 0.0) ** 2 + parts.get("solver", 0.0) ** 2 + scatter**2))
        check.update(steady_normal_force=normal, normal_error_estimate=relative * abs(normal))
    return check


def compute(name: str, overrides: dict | None = None, label: str | None = None) -> None:
    """The card of shape ``name`` and its consistency run, into ``OUT/<label>``."""
    label = label or name
    out = os.path.join(OUT, label)
    log = lambda line: print(line, file=sys.stderr, flush=True)  # noqa: E731
    card = bead_card(name, overrides=overrides, derivatives=DERIVATIVES.get(label, ()), progress=log)
    write_card(card, out)  # kept if the consistency run fails (``--recheck`` runs it again)
    write_card(card, out, extra={"consistency": consistency(name, overrides, out)})


def recheck(label: str) -> None:
    """The consistency run of the card ``label`` on disk again, its entry and files rewritten."""
    path = os.path.join(OUT, label, "bead_card.json")
    card = load_card(path)
    name = label.split("_")[0]
    write_card(card, os.path.dirname(path),
               extra={"consistency": consistency(name, card.overrides, os.path.dirname(path))})


def row(label: str) -> dict:
    with open(os.path.join(OUT, label, "bead_card.json")) as fh:
        s = json.load(fh)
    check = s.get("consistency") or {"steady_drawing_force": None, "error_estimate": None}
    full = s["restraining_force"][-1]
    out = {"shape": label, "H": s["depth"], "restraining_force": full, "bending_force": s["bending_force"][-1],
           "friction_force": s["friction_force"][-1], "normal_force": s["normal_force"][-1],
           "line_friction": s["line_friction"],
           "scatter": s["scatter"][-1], "thinning": s["thinning"][-1], "eqps_after": s["eqps_after"][-1],
           "eqps_after_max": s["eqps_after_max"][-1],
           "full_run_force": check["steady_drawing_force"], "full_run_error": check["error_estimate"],
           "full_run_normal_force": check.get("steady_normal_force"),
           "full_run_normal_error": check.get("normal_error_estimate"),
           "difference": None if check["steady_drawing_force"] is None else full - check["steady_drawing_force"],
           "full_run_converged": check.get("converged"), "penalty_runs": len(s.get("notes", []))}
    return out


def rewrite(label: str) -> None:
    """The files of the card ``label`` written again from its JSON, its consistency entry kept."""
    path = os.path.join(OUT, label, "bead_card.json")
    with open(path) as fh:
        check = json.load(fh).get("consistency")
    write_card(load_card(path), os.path.dirname(path), extra=None if check is None else {"consistency": check})


def derivative_rows(label: str) -> list[dict]:
    """One row per penetration of a card with derivatives: d(restraining, normal force) / d(field)."""
    with open(os.path.join(OUT, label, "bead_card.json")) as fh:
        s = json.load(fh)
    out = []
    for k, d in enumerate(s["penetration"]):
        r = {"shape": label, "penetration": d}
        for name, values in s["derivatives"].items():
            for short, output in (("F", "restraining_force"), ("Fb", "bending_force"), ("N", "normal_force"),
                                  ("thinning", "thinning"), ("eqps", "eqps_after"), ("eqps_max", "eqps_after_max")):
                if output in values:
                    r[f"d{short}_d{name}"] = values[output][k]
        out.append(r)
    return out if s["derivatives"] else []


def figure(labels: list[str], path: str) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(13, 4.8), constrained_layout=True)
    colours = plt.get_cmap("tab10")
    for k, label in enumerate(labels):
        with open(os.path.join(OUT, label, "bead_card.json")) as fh:
            s = json.load(fh)
        d = np.asarray(s["penetration"]) / s["depth"]
        style = {"color": colours(k % 10), "ls": "--" if label.startswith("shape1_") else "-", "marker": "o"}
        axes[0].plot(d, s["restraining_force"], label=label, **style)
        axes[1].plot(d, s["normal_force"], label=label, **style)
    for ax, what in zip(axes, ("restraining force", "normal (opening) force"), strict=True):
        ax.set(xlabel="penetration / bead height H", ylabel=f"{what} (N/mm)", title=f"bead cards: {what}")
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8, ncols=2)
    fig.savefig(path, dpi=110)
    print(f"written {path}")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--only", nargs="+", choices=SHAPES)
    p.add_argument("--kinematic", action="store_true", help="shape1's card with a back stress")
    p.add_argument("--s355", action="store_true", help="shape1's card with a published steel's cyclic fit and "
                   "with the isotropic law of its monotonic curve")
    p.add_argument("--table", action="store_true", help="only read back the cards on disk")
    p.add_argument("--rewrite", action="store_true", help="write the cards' files again from their JSON")
    p.add_argument("--recheck", nargs="+", choices=LABELS, metavar="LABEL",
                   help="run these cards' consistency runs again (their files rewritten), then the table")
    a = p.parse_args(argv)
    if a.recheck:
        for label in a.recheck:
            recheck(label)
    elif a.rewrite:
        for label in LABELS:
            if os.path.exists(os.path.join(OUT, label, "bead_card.json")):
                rewrite(label)
    elif not a.table:
        for name in a.only or ([] if a.kinematic or a.s355 else SHAPES):
            compute(name)
        if a.kinematic:
            compute("shape1", KINEMATIC, "shape1_kinematic")
        if a.s355:
            for label, law in S355.items():
                compute("shape1", law, label)
        if a.only or a.kinematic or a.s355:
            return 0
    labels = [s for s in LABELS if os.path.exists(os.path.join(OUT, s, "bead_card.json"))]
    if not labels:
        print("no card on disk", file=sys.stderr)
        return 1
    rows = [row(label) for label in labels]
    for r in rows:
        print(r)
    write_rows(os.path.join(HERE, "results", "bead_cards.csv"), rows)
    derived = [r for label in labels for r in derivative_rows(label)]
    if derived:
        write_rows(os.path.join(HERE, "results", "bead_cards_derivatives.csv"), derived)
    figure(labels, os.path.join(HERE, "results", "bead_cards.png"))
    return 0


if __name__ == "__main__":
    sys.exit(main())
