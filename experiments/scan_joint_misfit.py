"""The windowed misfit of the joint (mu, R1) fit of the Nine test along the straight line from the
point where the fits stalled, (0.1496, 5.366), to the truth (0.17, 5.5): ``python
experiments/scan_joint_misfit.py``. Each point is an ordinary adaptive run (penalty, 100 x 2, U_draw
10 mm); the misfit is half the sum of squares of the 1 mm window means against the run at the truth,
as in ``jaxfric.identification.fit``. Prints one line per point (t = 0: the stall point, t = 1: the truth).
"""

import numpy as np

import jaxfric as jf
from jaxfric import scenes
from jaxfric.identification.fit import bin_means

base = {"mesh": "100x2", "U_draw": 10.0}
def curve(mu, R1):
    sc = scenes.make("nine", "mu017", "penalty", {**base, "mu": mu, "R1": R1})
    r = jf.run(sc.model, control=sc.control, observe=sc.observe, progress=False)
    h = r.history
    return np.asarray(h["drawing_displacement"]), np.asarray(h["drawing_force"]), int(np.sum(h["cutbacks"]))
x, f, _ = curve(0.17, 5.5)
keep = x > 0
x, f = x[keep], f[keep]
edges = np.linspace(x[0], x[-1], int((x[-1] - x[0]) // 1.0) + 1)
obs = bin_means(x, f, edges)
a, b = np.array([0.1496, 5.366]), np.array([0.17, 5.5])
for t in np.linspace(-0.25, 1.0, 11):
    p = a + t * (b - a)
    xs, fs, cuts = curve(*p)
    k = xs > 0
    m = bin_means(xs[k], fs[k], edges)
    r = m - obs
    print(f"t {t:+.3f} mu {p[0]:.5f} R1 {p[1]:.4f} misfit {0.5 * float(r @ r):.4f} cuts {cuts}", flush=True)
