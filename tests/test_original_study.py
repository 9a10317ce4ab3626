"""Numbers of the original study (Chabrand, Dubois, Graillet, Boman and Ponthot 2005) that the
benchmark spec's inputs determine, checked on the spec's scenes at their spec meshes."""

import numpy as np
import pytest

from jaxfric.io.instants import steady_drawing_force
from jaxfric.loadpath.run import run
from jaxfric.scenes import make


def _converged_run(scene_name, variant, algorithm, overrides=None, snapshots=False):
    """The scene's run to its end (with the scene's snapshots at every step if ``snapshots``), asserted
    converged."""
    scene = make(scene_name, variant, algorithm, overrides)
    result = run(scene.model, newton=scene.newton, control=scene.control, observe=scene.observe,
                 snapshot=scene.snapshot if snapshots else None, progress=False)
    assert result.converged, result.message
    return scene, result


@pytest.fixture(scope="module")
def flat_die():
    """Both flat-die variants at the spec defaults (240 x 2, drawn 0.03 mm), penalty law."""
    out = {}
    for variant in ("const_force", "const_position"):
        out[variant] = _converged_run("flat_die", variant, "penalty")[1].history
    return out


def _sliding(h) -> int:
    """The first draw step at which every closed pair slips (the spec's ``sliding`` instant)."""
    draw = h["phase_name"] == "draw"
    return int(np.flatnonzero(draw & (h["n_active"] > 0) & (h["n_slip"] == h["n_active"]))[0])


@pytest.mark.xla_optimized   # mostly run time (tests/conftest.py)
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
      left-end constraint reached 6.1 times on 300 x 3, experiments/nine_tail_exit.py);
    - once the tail is past A (tail_x > R1), the drawing force below 0.75 times the steady one (the wrap
      on A and the guide's couple are gone: measured 0.47 at mu017 on 100 x 2, 0.59 and 0.52 for
      mu000 and mu017 on 300 x 3, where the bending over B and C remains)."""
    scene, result = _converged_run("nine", variant, "lcp_ssn", {"mesh": "100x2", "U_draw": 62.0}, snapshots=True)
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


# The Nine's steady force converged along the strip and through the thickness (N/mm, U_draw 36 mm,
# 0.05 mm increments, lcp_ssn, v = 0 on the left-end nodes), uncertain by about 0.8 %: from the runs of
# ``ans`` up to 600 x 12 and ``anst`` up to 1200 x 6 (``python experiments/nine_error_sources.py``;
# docs/results.md, "Layers through the thickness").
NINE_CONVERGED = {"mu000": 82.6, "mu017": 144.8}


@pytest.mark.slow  # two Nine runs at the spec mesh, U_draw 36 mm, about 2 to 4 minutes each
@pytest.mark.parametrize("variant", ["mu000", "mu017"])
def test_nine_spec_mesh_within_four_percent_of_the_converged_force(variant):
    """The study finds the 300 x 3 mesh within 4 % of its finest. Here the steady force on 300 x 3 (default
    element, the reference's increments and entry guide) against the force converged in both directions
    (NINE_CONVERGED): tolerance 4 %, the study's statement (measured with ``ans``: -1.9 % and +0.4 %, the
    3 layers' error and the element length's partly cancelling; F-bar, the element the spec names, gives
    +3.4 % and +6.1 %). The project's goal of 1 % at the spec mesh is not reached (docs/results.md)."""
    scene, result = _converged_run("nine", variant, "lcp_ssn", {"U_draw": 36.0, "dq_clamp": 0.05, "dU": 0.05,
                                                                "entry_guide_kind": "end_nodes"})
    force = steady_drawing_force(result.history, scene.steady_window)
    assert force == pytest.approx(NINE_CONVERGED[variant], rel=0.04), force


@pytest.mark.slow  # two bead runs at the spec mesh, about 2 minutes each
def test_bead_wrap_follows_bending_under_tension():
    """The roller's wrap (th090) against the bending-under-tension relation F = T e^(mu theta') + F_bend:
    - T is the back tension that the clamp's friction holds (``clamp_ft``: 2 mu_clamp F_clamp = 204 N/mm
      once the clamp slides);
    - F_bend = F - T of the frictionless roller (th090_mu000; th135_mu000 gives the same 44.04 N/mm);
    - theta' = theta R_r / (R_r + t / 2): the friction acts on the roller's surface, the tension at the
      strip's mid-thickness, and the bending moments at both ends of the wrap are equal, so the moments
      about the roller's centre give dT (R_r + t / 2) = mu R_r dN (on this thick strip, R_r / t = 3.3, the
      run is 2.9 % below the thin-belt relation's mu theta).
    Mean values over the steady window. Tolerance 1 %, for what the relation leaves out (the tension's
    effect on the bending work, the contact arc's ends); measured +0.08 %, and -0.43 % on th135. On th045
    the relation is 2.1 % low: a 45 degree wrap does not bend the strip to the roller's curvature (F_bend
    38.46 N/mm). A roller without friction is 20 % off, twice its friction 30 %."""
    steady = {}
    for variant in ("th090_mu000", "th090_mu017"):
        scene, result = _converged_run("bead", variant, "lcp_ssn")
        h = result.history
        window = (h["phase_name"] == "draw") & (h["drawing_displacement"] >= scene.steady_window[0])
        steady[variant] = (np.mean(h["drawing_force"][window]), np.mean(h["clamp_ft"][window]))
    config = scene.config
    back_tension = 2 * config.mu_clamp * config.F_clamp
    assert all(t == pytest.approx(back_tension, rel=0.01) for _, t in steady.values()), steady
    (f0, t0), (f1, t1) = steady["th090_mu000"], steady["th090_mu017"]
    wrap = np.deg2rad(config.theta) * config.R_r / (config.R_r + config.t / 2)
    predicted = t1 * np.exp(config.mu_roller * wrap) + (f0 - t0)
    assert f1 == pytest.approx(predicted, rel=0.01), (f1, predicted)
