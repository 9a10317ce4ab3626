"""A Nine identification in the fast suite on a curve the fitting model did not make.

The data: the drawing force of ``experiments/fit_bias_mesh.py``'s reference (``nine --variant mu017``,
mu = 0.17, exact contact on 1200 x 3 at half the nominal increments: the accuracy tests' reference
discretisation of the Nine), its first 3 mm of draw. The fit: the README's command at the recommended fit
mesh, 100 x 2, on that stroke (``jaxfric fit nine --param mu --mesh 100x2 --set U_draw=3 --set mu=0.12
--window 1``). The fitting model differs from the data's by its mesh (twelve times coarser along the
strip, 2 layers for 3) and its increments; what it recovers is mu with that model error in it. The
full-stroke fits against mesh and the other data (noise, another algorithm, another material) are the
experiment's (docs/results.md, identification).
"""

import csv
import os

import numpy as np
import pytest

from jaxfric.identification.fit import fit

DATA = os.path.join(os.path.dirname(__file__), os.pardir, "experiments", "results", "fit_bias_mesh", "reference.csv")


@pytest.mark.xla_optimized   # mostly run time (tests/conftest.py)
def test_nine_mu_from_a_finer_exact_model_at_the_recommended_fit_mesh():
    with open(DATA, newline="") as fh:
        rows = list(csv.DictReader(fh))
    u = np.array([float(r["drawing_displacement"]) for r in rows])
    f = np.array([float(r["drawing_force"]) for r in rows])
    keep = u <= 3.0 + 1e-9
    res = fit("nine", {"drawing_displacement": u[keep], "drawing_force": f[keep]}, ["mu"], variant="mu017",
              overrides={"mesh": "100x2", "U_draw": 3.0, "mu": 0.12}, window=1.0, progress=False)
    assert res.converged, res.message
    # The goal: within 0.005 of the truth (measured: 0.1724, the model error of 100 x 2 against
    # 1200 x 3 over the first 3 mm of draw), and an interval that holds it.
    assert abs(res.params["mu"] - 0.17) < 0.005, res.params
    lo, hi = res.ci95["mu"]
    assert lo <= 0.17 <= hi
    assert res.n_simulations <= 8
