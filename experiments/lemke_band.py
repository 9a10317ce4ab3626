"""Lemke's proximity band on the blankholder's long lands: ``python experiments/lemke_band.py``.

    python experiments/lemke_band.py [--variant shape4] [--pull MM] [--bands 256 512 none]

The blankholder variant with ``lcp_lemke`` at its default band runs close and lock and stops at the start
of the draw (the first chunk past t = 2); from that checkpoint the draw (``U_pull`` = ``--pull`` mm, a
short pull) runs again at each band of ``--bands`` (``none``: every candidate node), after ``lcp_ssn``
(every candidate, in-loop) has run the whole path (its row: its steps after that time). Per row: the
draw's steps, Newton iterations, Lemke pivots, the steps cut per cause (history ``cut_codes``), the band's widenings
(``Result.BAND_FULL``), the draw's solve time (s; one process, so run it pinned to a core of its own),
the largest numbers of closed pairs in the draw, and the drawing force at the end. Writes
``experiments/results/lemke_band_<variant>.csv``.
"""

from __future__ import annotations

import argparse
import os

import equinox as eqx
import numpy as np

import jaxfric as jf
from benchutil import write_rows
from jaxfric import scenes
from jaxfric.numerics.results import causes

HERE = os.path.dirname(os.path.abspath(__file__))


def _draw_row(label: str, band, res, first_row: int, solve_s: float) -> dict:
    h = res.history
    cut: dict[str, int] = {}
    for mask in h["cut_codes"][first_row:]:
        for name in causes(int(mask)):
            cut[name] = cut.get(name, 0) + 1
    return {"algorithm": label, "band": "all" if band is None else band, "converged": res.converged,
            "draw_steps": len(h["time"]) - first_row, "newton_iters": int(h["newton_iters"][first_row:].sum()),
            "lcp_pivots": int(h["lcp_pivots"][first_row:].sum()),
            "cut_causes": " ".join(f"{k}:{n}" for k, n in cut.items()),
            "band_widened": " ".join(f"{b}@{t:.6g}" for t, b in res.band_widened),
            "solve_s": round(solve_s, 2), "max_closed": int(h["n_active"][first_row:].max()),
            "final_time": float(h["time"][-1]), "final_drawing_force": float(h["drawing_force"][-1])}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--variant", default="shape4")
    p.add_argument("--pull", type=float, default=3.0, help="U_pull (mm)")
    p.add_argument("--bands", nargs="+", default=["256", "512", "none"])
    opts = p.parse_args()
    overrides = {"U_pull": opts.pull}
    sc = scenes.make("blankholder", opts.variant, "lcp_lemke", overrides)
    kw = dict(newton=sc.newton, control=sc.control, observe=sc.observe, progress=False, raise_on_failure=False)
    reached = {"t": 0.0}

    def on_chunk(partial):
        reached["t"] = float(partial().history["time"][-1])

    first = jf.run(sc.model, **kw, on_chunk=on_chunk, stop=lambda: reached["t"] >= 2.0)
    n0 = len(first.history["time"])
    print(f"close and lock: {n0 - 1} steps to t = {float(first.history['time'][-1]):.6g}, "
          f"{first.wall_s:.1f} s", flush=True)
    out = os.path.join(HERE, "results", f"lemke_band_{opts.variant}.csv")
    rows: list[dict] = []
    ssn = scenes.make("blankholder", opts.variant, "lcp_ssn", overrides)
    res = jf.run(ssn.model, newton=ssn.newton, control=ssn.control, observe=ssn.observe, progress=False,
                 raise_on_failure=False)
    k = int(np.searchsorted(res.history["time"], float(first.history["time"][-1]), side="right"))
    draw_s = float(res.history["wall_s"][k:].sum())
    rows.append(_draw_row("lcp_ssn", None, res, k, draw_s))
    print(rows[-1], flush=True)
    write_rows(out, rows)   # row by row: a band that takes hours can be stopped
    for text in opts.bands:
        band = None if text == "none" else int(text)
        model = eqx.tree_at(lambda m: m.contact, sc.model, sc.model.contact.with_band(band))
        res = jf.run(model, **kw, resume=first.checkpoint)
        rows.append(_draw_row("lcp_lemke", band, res, n0, res.wall_s - first.wall_s))
        print(rows[-1], flush=True)
        write_rows(out, rows)


if __name__ == "__main__":
    main()
