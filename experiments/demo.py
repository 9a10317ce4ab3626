"""Demo of the core solver: ``python experiments/demo.py [--out DIR] [--mesh NXxNY]``.

Stretches and bends an elasto-plastic strip (``experiments/strips.py``), with a
progress bar, then writes ``forces.png`` (end reactions against pseudo-time) and ``mesh.png`` (deformed
mesh coloured by equivalent plastic strain) into DIR.
"""

from __future__ import annotations

import argparse
import os
import sys

import numpy as np


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python experiments/demo.py", description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="demo_out", help="output directory (default: demo_out)")
    parser.add_argument("--mesh", default="300x3", help="NXxNY elements (default: 300x3)")
    args = parser.parse_args(argv)
    try:
        nx, ny = (int(v) for v in args.mesh.lower().split("x"))
    except ValueError:
        print(f"error: --mesh must look like 300x3, got {args.mesh!r}", file=sys.stderr)
        return 2

    import jaxfric as jf
    from jaxfric.io.plotting import element_values_mean, figure, plot_mesh
    from strips import stretch_bend_strip

    try:
        model = stretch_bend_strip(nx=nx, ny=ny)
    except ValueError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    result = jf.run(model, raise_on_failure=False, label="stretch-bend ")
    h = result.history
    os.makedirs(args.out, exist_ok=True)

    fig, ax = figure(1000, 600)
    ax.plot(h["time"], h["reaction_right"][:, 0], label="right end, x reaction")
    ax.plot(h["time"], h["reaction_right"][:, 1], label="right end, y reaction")
    ax.axvline(1.0, ls="--", c="0.5", lw=0.8)
    ax.set_xlabel("pseudo-time (phase 1: stretch, phase 2: bend)")
    ax.set_ylabel("reaction (N/mm)")
    ax.set_title(f"stretch-bend strip {nx}x{ny}: end reactions")
    ax.legend()
    fig.savefig(os.path.join(args.out, "forces.png"))

    fig, (ax_all, ax_end) = figure(1400, 800, nrows=2, gridspec_kw=dict(height_ratios=[1, 2]))
    eqps = element_values_mean(result.final.material.eqps)
    x = np.asarray(model.mesh.nodes) + result.final.u
    plot_mesh(ax_all, x, model.mesh.elements, eqps, label=f"deformed strip {nx}x{ny}, final state")
    coll = plot_mesh(ax_end, x, model.mesh.elements, eqps, label="right end (plastic hinge), zoomed")
    right = x[model.mesh.right]
    ax_end.set_xlim(right[:, 0].min() - 4.0, right[:, 0].max() + 0.5)
    ax_end.set_ylim(right[:, 1].min() - 0.5, right[:, 1].max() + 0.5)
    fig.colorbar(coll, ax=[ax_all, ax_end], label="equivalent plastic strain")
    fig.savefig(os.path.join(args.out, "mesh.png"))

    n_steps = len(h["time"]) - 1
    print(f"{'converged' if result.converged else 'STOPPED: ' + result.message}")
    print(f"steps {n_steps}, Newton iterations {int(h['newton_iters'].sum())}, cutbacks "
          f"{int(h['cutbacks'].sum())}, compile {result.compile_s:.2f} s, solve {result.wall_s:.2f} s")
    print(f"max equivalent plastic strain {float(np.max(eqps)):.4f}")
    print(f"plots: {os.path.join(args.out, 'forces.png')}, {os.path.join(args.out, 'mesh.png')}")
    return 0 if result.converged else 1


if __name__ == "__main__":
    sys.exit(main())
