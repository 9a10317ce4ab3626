"""Numbers of the original study (Chabrand, Dubois, Graillet, Boman and Ponthot 2005) that the
benchmark spec's inputs determine, checked on the spec's scenes at their spec meshes."""

import numpy as np
import pytest

from jaxfric.loadpath.run import run
from jaxfric.scenes import make


@pytest.fixture(scope="module")
def flat_die():
    """Both flat-die variants at the spec defaults (240 x 2, drawn 0.03 mm), penalty law."""
    out = {}
    for variant in ("const_force", "const_position"):
        scene = make("flat_die", variant, "penalty")
        result = run(scene.model, newton=scene.newton, control=scene.control, observe=scene.observe,
                     progress=False)
        assert result.converged, result.message
        out[variant] = result.history
    return out


def _sliding(h) -> int:
    """The first draw step at which every closed pair slips (the spec's ``sliding`` instant)."""
    draw = h["phase_name"] == "draw"
    return int(np.flatnonzero(draw & (h["n_active"] > 0) & (h["n_slip"] == h["n_active"]))[0])


def test_flat_die_const_force_slides_where_the_study_says(flat_die):
    """Constant die force: global sliding sets in at a drawing displacement of 0.01064 mm in the study.
    The run can only place it at the end of one of its 1e-4 mm draw increments (0.9 % of the value), and
    its mesh is the spec's, not necessarily the study's: tolerance 2 % (measured: between 0.0104 and
    0.0105 mm, -1.3 %). Once sliding, the drawing force is mu P = 0.15 x 50 N/mm."""
    h = flat_die["const_force"]
    k = _sliding(h)
    assert h["drawing_displacement"][k] == pytest.approx(0.01064, rel=0.02)
    np.testing.assert_allclose(h["drawing_force"][k:], 0.15 * 50.0, rtol=1e-6)


def test_flat_die_const_position_ends_at_the_study_s_normal_force(flat_die):
    """Die held where the clamp left it: the normal force falls as the strip is drawn and thins, to 6.37
    N/mm at the end in the study (given to three digits). Tolerance 1 %, the accuracy the project asks
    of its spec meshes (measured: 6.398 N/mm, +0.4 %). The strip then slides at mu times that force."""
    h = flat_die["const_position"]
    assert h["clamping_force"][-1] == pytest.approx(6.37, rel=0.01)
    assert h["drawing_force"][-1] == pytest.approx(0.15 * h["clamping_force"][-1], rel=1e-6)


@pytest.mark.slow  # two Nine runs at 100 x 2, about 40 s each (make test-all)
@pytest.mark.parametrize("variant", ["mu000", "mu017"])
def test_nine_forces_drop_when_the_tail_passes_the_bead(variant):
    """The study reports a steady drawing force, then a drop when the sheet's end is swallowed by the
    bead. With the entry guide's channel the tail leaves the guide after the steady window and passes
    the bead freely. Checked on the coarse fitting mesh 100 x 2 (exact contact, the nominal increments):
    - after the window, no drawing force above 1.3 times the steady one (the issue's goal; measured
      1.13x at mu017, from the coarse mesh's node-passing ripple of about +/- 10 %);
    - no runaway plastic strain: the run's largest equivalent plastic strain within 1.5 times the
      largest in the steady window (measured 1.11x at mu017; the tail dragged into the bead by the
      left-end constraint reached 5.6 times on 300 x 3, experiments/nine_tail_exit.py);
    - once the tail is past A (tail_x > R1), the drawing force below 0.75 times the steady one (the wrap
      on A and the guide's couple are gone: measured 0.47 at mu017 on 100 x 2, 0.59 and 0.52 for
      mu000 and mu017 on 300 x 3, where the bending over B and C remains)."""
    scene = make("nine", variant, "lcp_ssn", {"mesh": "100x2", "U_draw": 62.0})
    result = run(scene.model, newton=scene.newton, control=scene.control, observe=scene.observe,
                 snapshot=scene.snapshot, progress=False)
    assert result.converged, result.message
    h = result.history
    u, force, tail = h["drawing_displacement"], h["drawing_force"], h["tail_x"]
    draw = h["phase_name"] == "draw"
    window = draw & (u >= 20.0) & (u <= 35.0)
    steady = np.mean(force[window])
    after = draw & (u > 35.0)
    assert u[-1] == pytest.approx(62.0)
    assert np.max(force[after]) <= 1.3 * steady, (np.max(force[after]), steady)
    eqps = np.array([np.max(result.snapshots[k]["eqps"]) for k in range(len(u))])
    assert np.max(eqps) <= 1.5 * np.max(eqps[window]), (np.max(eqps), np.max(eqps[window]))
    past_a = draw & (tail > scene.config.R1)
    assert np.any(past_a)
    assert np.max(force[past_a]) <= 0.75 * steady, (np.max(force[past_a]), steady)
