"""Where the semismooth Newton's active-set passes go: per Newton iteration, how many passes, and per pass
after the first, which candidate nodes changed status, from what to what, on which tool.

    python experiments/ssn_passes.py [--scene nine] [--variant mu017] [--set U_draw=3 ...] [--from-u 0.3]

Runs the scene with exact contact (``lcp_ssn``) on one device, recording every pass's active set from the
host (``jax.debug.callback`` around :func:`jaxfric.contact.exact_active_set.piece_system`, which each pass
calls once, and around :func:`~jaxfric.contact.exact_active_set.active_set_step`, called once per Newton
iteration). Counts only the iterations where the largest prescribed displacement is ``--from-u`` mm or more
(on the Nine: the pull, so the draw from U = 0.3 mm on by default).
Writes ``results/ssn_passes.csv`` (one row per tool: status changes between successive passes, by kind)
and ``results/ssn_passes_iterations.csv`` (how many Newton iterations took each number of passes).
"""

from __future__ import annotations

import argparse
import collections
import csv
import os

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

import jaxfric.contact.exact as exact  # noqa: E402
import jaxfric.contact.exact_active_set as active  # noqa: E402
from jaxfric import scenes  # noqa: E402
from jaxfric.contact.alart_curnier import OPEN, STICK  # noqa: E402
from jaxfric.contact.exact_iterate import pair_tools  # noqa: E402
from jaxfric.loadpath.run import run  # noqa: E402

HERE = os.path.dirname(os.path.abspath(__file__))
KINDS = ("open_to_closed", "closed_to_open", "stick_to_slip", "slip_to_stick", "slip_reversed")


class Recorder:
    """The passes of each Newton iteration, as the run's program reports them (host side)."""

    def __init__(self):
        self.iterations: list[dict] = []

    def iteration(self, pull):
        self.iterations.append({"pull": float(pull), "passes": []})

    def active_set(self, state, tool):
        self.iterations[-1]["passes"].append((np.asarray(state), np.asarray(tool)))


def instrument(recorder: Recorder):
    """Wrap the solver's pass and iteration so that they report to ``recorder`` (before any tracing)."""
    piece_system, active_set_step = active.piece_system, exact.active_set_step

    def piece_system_recorded(d, args, state):
        tool = jax.numpy.asarray(pair_tools(args.contact.tools))[d.fr.pairs]
        jax.debug.callback(recorder.active_set, state, tool, ordered=True)
        return piece_system(d, args, state)

    def active_set_step_recorded(it, args, x, p, law, hint, frames=None):
        jax.debug.callback(recorder.iteration, jax.numpy.max(jax.numpy.abs(args.values)), ordered=True)
        return active_set_step(it, args, x, p, law, hint, frames=frames)

    active.piece_system = piece_system_recorded
    exact.active_set_step = active_set_step_recorded


def changes(before, after):
    """Per kind, a mask of the nodes whose status went from ``before`` to ``after``."""
    closed_b, closed_a = before != OPEN, after != OPEN
    slip_b, slip_a = closed_b & (before != STICK), closed_a & (after != STICK)
    return {"open_to_closed": ~closed_b & closed_a, "closed_to_open": closed_b & ~closed_a,
            "stick_to_slip": (before == STICK) & slip_a, "slip_to_stick": slip_b & (after == STICK),
            "slip_reversed": slip_b & slip_a & (before != after)}


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="nine")
    ap.add_argument("--variant", default="mu017")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="scene overrides")
    ap.add_argument("--from-u", type=float, default=0.3,
                    help="count the iterations whose largest prescribed displacement (mm) is this or more")
    ap.add_argument("--out", default=os.path.join(HERE, "results", "ssn_passes.csv"))
    a = ap.parse_args(argv)

    overrides = dict(kv.split("=", 1) for kv in a.set) or {"U_draw": "3"}
    recorder = Recorder()
    instrument(recorder)
    scene = scenes.make(a.scene, a.variant, "lcp_ssn", overrides)
    result = run(scene.model, newton=scene.newton, control=scene.control, observe=scene.observe,
                 progress=False, raise_on_failure=False)
    names = [t.name for t in scene.model.tools]
    counted = [it for it in recorder.iterations if it["pull"] >= a.from_u and it["passes"]]
    passes = np.array([len(it["passes"]) for it in counted])
    table = {name: collections.Counter() for name in names}
    for it in counted:
        for (before, tool), (after, _) in zip(it["passes"], it["passes"][1:]):
            for kind, mask in changes(before, after).items():
                for k, name in enumerate(names):
                    table[name][kind] += int(np.sum(mask & (tool == k)))
    os.makedirs(os.path.dirname(a.out), exist_ok=True)
    with open(a.out, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["tool", *KINDS, "total"])
        for name in names:
            w.writerow([name, *(table[name][k] for k in KINDS), sum(table[name].values())])
    hist = collections.Counter(np.minimum(passes, 10).tolist())
    with open(a.out.replace(".csv", "_iterations.csv"), "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["passes", "iterations"])
        w.writerows(sorted(hist.items()))
    print(f"{a.scene} {a.variant} {overrides}: code {int(result.code)}; from U = {a.from_u} mm: {len(counted)} Newton "
          f"iterations, {passes.sum()} passes ({passes.mean():.2f} per iteration); iterations by passes "
          f"(10: 10 or more): {dict(sorted(hist.items()))}")
    for name in names:
        print(f"  {name:>12}: " + ", ".join(f"{k} {table[name][k]}" for k in KINDS))
    print(f"written {a.out}")


if __name__ == "__main__":
    main()
