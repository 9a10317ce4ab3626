"""Extreme inputs: every scene at its edges, each case converged with physical checks or a clean,
explained failure (a result code, a message naming the step, time and phase, finite results kept).

Every run below also checks (``_run``): no NaN or Inf in any history column nor in the final state,
at most ``StepControl.max_cuts`` + 2 cuts per accepted step, every cut recorded in ``history["cutbacks"]``
(the step controller replayed from the recorded times), and for a failed run a message naming the
last accepted step, time and phase, and a last attempt cut to the controller's limit.

Fast cases: the flat die (coarse 12 x 1 mesh, 4.8 mm long, drawn 0.006 mm with the spec's increments:
10 clamp + 135 draw steps). Changing values only (eps_n, mu, F_clamp, ...) reuses one compiled run.

- ``test_flat_die_penalty_range[1e2|1e5|1e9|1e12]``: eps_n over 1e2..1e12 N/mm (the spec's 1e9
  included) with eps_t = eps_n. The die's force balance sum R_N = P(t) at every step, mean <= max
  penetration * eps_n <= total force, -g = R_N / eps_n on every closed pair, x-equilibrium of the
  strip (drawing force = |sum R_T|), Coulomb at every step and pair; global sliding at mu P for
  eps_n >= 1e5 (at 1e2 the tangential penalty's elastic slip, 5.8e-3 mm, is about the whole draw).
- ``test_flat_die_friction[0.5|1.0]``: mu = 0.5 (global sliding at 0.5 P), 1.0 (the strip yields
  before it slides: partial slip, drawing force < mu P); mu = 0 is a slow case (a frictionless tool is
  another compiled structure).
- ``test_auglag_target_gap``: AL with target gap 1e-8 mm (own compilation): max penetration <= 1e-8 mm
  at every step; eps_n = 1e2 with the same target is refused cleanly (AUGMENTATIONS).
- ``test_two_runs_are_identical``: two runs from two freshly built scenes agree to 1e-12.
- ``test_failed_steps_are_cut_and_recorded``: F_clamp = 5000 N/mm: steps fail, are cut, and the
  run recovers; every cut is in the history.
- ``test_cut_limit_stops_the_run_cleanly``: F_clamp = 1e6 N/mm: 10 cuts per step are not enough, the
  run stops with MAX_ITERATIONS after a bounded number of cuts.
- ``test_nonfinite_first_step`` (F_clamp = 1e300 N/mm) and ``test_nonfinite_mid_run`` (a pull of
  4e297 mm during draw): a non-finite residual stops the run with NONFINITE at the step where it
  appeared, every row kept is finite.

Slow cases (``-m slow``):

- ``test_flat_die_friction[0.0]``: no friction, no drawing force.
- ``test_flat_die_load_step[x10|x0.1]``: nominal increments 10x larger / smaller than the spec's;
  ``test_load_step_x10[nine|bead|blankholder]``: the other scenes' 10x larger, converged.
- ``test_flat_die_fine_mesh``: 12 elements through the half thickness (48 x 12).
- ``test_rotation_invariance_flat_die``: the flat die turned by exactly 90 degrees (its symmetry and
  draw conditions are componentwise); ``test_rotation_invariance_nine``: the Nine scene (free entry,
  so only full-node conditions) turned by 37 degrees; ``test_rotation_invariance_bead_and_blankholder``:
  the bead and the blankholder with exact contact, turned by 37 degrees.
- ``test_nine_edges[...]``: mu 0.5 / 1.0, ny 1 / 12, t/R1 0.02 / 0.5, eps_n 1e2 / 1e9 / 1e12 (the
  stiff ones with the scenes' StiffPenalty, above 100 times their spec penalty), the
  bead B pushed to full clearance (stroke 2 R1 = 11 mm: B's gap to A and C is then 1.04 t).
- ``test_bead_edges[...]``: mu 0.5 / 1.0 (roller; clamp dies too), ny 1 / 12, t/R_r 0.02 (0.7 mm over a
  35 mm roller, 4 layers) / 0.5, a 0.1 mm foil over the 5 mm roller,
  eps_n 1e2 / 1e9 / 1e12.
- ``test_blankholder_edges[...]``: the bead closed to full clearance (s = H) on a frictionless sheet,
  ny 1 / 12, t/R 0.02 / 0.5, eps_n 1e2 / 1e9 / 1e12, and mu 0.15 / 0.5 / 1.0.
- ``test_force_driven_tool_loses_and_regains_contact[...]``: the release/drop/press cycle of
  tests/test_contact.py (eps_n = 1e9 there) with eps_n = 1e2, 1e12 and AL (target 1e-8 mm).

Every edge case must converge and pass the physical checks; the deliberate failures (a target gap the
penalty cannot reach, a load no increment carries, non-finite input, a stiff penalty with the plain
law) are tests of their own, which check the clean stop. Set ``JAXFRIC_EXTREME_TABLE=path`` to write a
markdown table of every run (case, outcome, steps, cuts, Newton iterations, wall time, last residual).
"""

import dataclasses
import math
import os
import re
import types

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxfric as jf
from jaxfric.contact.formulations import STIFF_PENALTY_RATIO, AugmentedLagrangian, Penalty, StiffPenalty
from jaxfric.contact.rigid import Force, RigidTool
from jaxfric.contact.tools import Arc, Segment, Tool
from jaxfric.fem.loading import constraint_masks, schedule, with_steps
from jaxfric.loadpath.controller import STABILIZE_RISE
from jaxfric.loadpath.model import reactions
from jaxfric.loadpath.run import run
from jaxfric.loadpath.step import continuation_stages
from jaxfric.numerics.results import Result
from jaxfric.scenes import make

# The flat die of the fast cases: spec increments (dU_fine 2.5e-5 mm to 0.0025 mm, then dU 1e-4 mm,
# 10 clamp steps) on a short strip drawn until it slides globally.
FAST = {"mesh": "12x1", "L": 4.8, "U_draw": 0.006}
NINE = {"mesh": "30x2", "stroke": 3.0, "dq_clamp": 0.5, "U_draw": 1.0, "dU": 0.25}
BEAD = {"mesh": "100x2", "theta": 10.0, "dtheta": 2.5, "s_draw": 0.5, "ds": 0.25, "n_clamp": 2, "mu_clamp": 0.0}
BLANK = {"element_length": 1.0, "ds_close": 0.25, "n_lock": 2, "U_pull": 1.0, "dU": 0.25, "mu": 0.0}

_TABLE = []


# ---- running and the checks every run gets --------------------------------------------------------

@pytest.fixture(scope="module", autouse=True)
def _write_table():
    yield
    path = os.environ.get("JAXFRIC_EXTREME_TABLE")
    if path and _TABLE:
        lines = ["| case | outcome | steps | cuts | Newton iterations | stabilised steps (damper energy / drawing "
                 "work) | wall (s) | last residual (N/mm) |", "|---|---|---|---|---|---|---|---|"]
        lines += [f"| {' | '.join(row)} |" for row in _TABLE]
        with open(path, "a") as f:
            f.write("\n".join(lines) + "\n\n")


def _outcome(res) -> str:
    if res.converged:
        return "converged"
    where = re.match(r"stopped after (step \d+ at t = \S+ \(phase '\w+'\))", res.message)
    return f"failed: {res.code.name}, {where.group(1) if where else res.message}"


def _run(case, scene, observe=None, control=None):
    """Run ``scene`` without raising, record it for the table, and check what every run must satisfy."""
    res = run(scene.model, newton=scene.newton, control=control or scene.control, observe=observe or scene.observe,
              progress=False, raise_on_failure=False)
    h = res.history
    damped = int(np.count_nonzero(h["damping_energy"]))
    work = float(np.trapezoid(h["drawing_force"], h["drawing_displacement"])) if "drawing_force" in h else 0.0
    share = f" ({float(h['damping_energy'].sum()) / work:.2g})" if damped and work > 0 else ""
    _TABLE.append((case, _outcome(res), str(len(h["time"]) - 1), str(int(h["cutbacks"].sum())),
                   str(int(h["newton_iters"].sum())), f"{damped}{share}", f"{res.wall_s:.2f}",
                   f"{float(res.simulation.residual_norm):.3g}"))
    _assert_finite(res)
    _assert_cuts_recorded(scene, res, control or scene.control)
    if not res.converged:
        _assert_clean_failure(scene, res, control or scene.control)
    return res


def _assert_finite(res):
    for key, column in res.history.items():
        if column.dtype.kind in "fiu":
            assert np.all(np.isfinite(column)), f"non-finite values in history column {key!r}"
    for leaf in jax.tree_util.tree_leaves(res.final):
        assert np.all(np.isfinite(np.asarray(leaf))), "non-finite values in the final state"


def _nominal_dt(model, t_prev):
    """Nominal increment of the schedule segment that a step starting at ``t_prev`` belongs to."""
    sched = schedule(model.phases)
    seg = min(int(np.searchsorted(np.asarray(sched.seg_end), t_prev, side="right")), len(sched.seg_dt) - 1)
    return sched.seg_dt[seg]


def _stage_attempts(scene, control) -> int:
    """Attempts the penalty continuation of StepControl may add to a step at the smallest increment."""
    m = int(continuation_stages(scene.model))
    return m + 1 if control.continuation and m > 0 else 0


def _assert_cuts_recorded(scene, res, control):
    """Every cut is in ``history["cutbacks"]``, at most max_cuts + 2 (and the continuation's stages, and
    the two stabilised attempts) per accepted step.

    The controller (StepControl) halves a failed attempt, so a step recorded with k cuts started as an
    attempt of (its length) * 2**k, or 2**(k-1) where its first attempt was retried at its length.
    Without a failure it never shrinks the increment: within a schedule segment the first attempt is
    the previous step's length, or 1.5 times it after easy steps, capped by the nominal increment and
    clipped to the segment end; a new segment starts at its nominal increment.
    A missing (or extra) cut would put the reconstructed first attempt outside these bounds by a factor
    of at least 4/3.
    """
    h = res.history
    cuts = h["cutbacks"]
    stages = _stage_attempts(scene, control)
    # max_cuts halvings, the retry of a predicted first attempt, the unsearched attempt, the stages, the
    # stabilised attempts
    damped = 2 if control.stabilize > 0 else 0
    assert np.all(cuts >= 0) and np.all(cuts <= control.max_cuts + 2 + stages + damped), cuts.max()
    t = h["time"]
    assert np.all(np.diff(t) > 0)
    sched = schedule(scene.model.phases)
    ends = np.asarray(sched.seg_end)
    prev_dt, prev_seg = sched.seg_dt[0], 0
    for i in range(1, len(t)):
        seg = min(int(np.searchsorted(ends, t[i - 1], side="right")), len(ends) - 1)
        dt_nom, rest = sched.seg_dt[seg], ends[seg] - t[i - 1]
        if seg == prev_seg:
            lo, hi = min(prev_dt, rest), min(control.growth * prev_dt, dt_nom, rest)
        else:
            lo = hi = min(dt_nom, rest)
        dt = t[i] - t[i - 1]
        # A failed first attempt from the secant prediction is attempted again at its length from the
        # converged state (that cut did not halve). Where halving would go below the smallest increment
        # the same length is attempted again: once from the converged state if the failed attempt was
        # the step's first, then in the penalty continuation's stages, then once with Newton's line
        # search off, then in the stabilised attempts.
        floor = dt < 2 * dt_nom / 2.0 ** control.max_cuts * (1 + 1e-6)
        repeats = range(min(int(cuts[i]), 2 + stages + damped if floor else 1) + 1)
        firsts = [dt * 2.0 ** (cuts[i] - r) for r in repeats]
        assert any(lo * (1 - 1e-6) <= f <= hi * (1 + 1e-6) for f in firsts), \
            (i, t[i - 1], t[i], int(cuts[i]), lo, hi)
        prev_dt, prev_seg = t[i] - t[i - 1], seg


def _assert_clean_failure(scene, res, control):
    """A failed run: a result code, a message naming the last accepted step, its time and phase and
    what to try, the rows up to it kept (finite, checked by _assert_finite), and, unless the history
    buffer was full, a last attempt cut to the controller's limit (nominal / 2**max_cuts)."""
    h = res.history
    n = len(h["time"]) - 1
    assert res.code not in (Result.SUCCESS, Result.CONTINUE)
    assert res.message.startswith(f"stopped after step {n} at t = "), res.message
    phase = scene.model.phases[int(res.final.phase)].name
    assert f"(phase '{phase}')" in res.message and res.message.endswith("are kept."), res.message
    assert h["time"][-1] == float(res.final.time)
    if res.code != Result.MAX_STEPS:
        t_fail = float(res.simulation.failed_time)
        dt_nom = _nominal_dt(scene.model, float(res.final.time))
        assert 0 < t_fail - float(res.final.time) < 2 * dt_nom / 2.0**control.max_cuts * (1 + 1e-9), \
            (t_fail, float(res.final.time), dt_nom)
        # The failed attempts of the step that stopped the run (no history row holds them) are
        # reported: max_cuts + 1 lengths, the last one attempted again in the continuation's stages (the
        # penalty law) and without the line search (exact contact has none); fewer when that step
        # started below the nominal increment.
        cuts = int(res.simulation.pending_cuts)
        searched = scene.model.contact.unsearched_retry
        stages = _stage_attempts(scene, control)
        assert 1 + searched <= cuts <= control.max_cuts + 1 + searched + stages, cuts
        assert f"after {cuts} failed attempt" in res.message, res.message


# ---- physical checks ----------------------------------------------------------------------------

def _pair_forces(contact):
    """(m, 2) force on the sheet of every pair, R_N n + R_T t with t = (-n_y, n_x)."""
    n = np.asarray(contact.normal)
    tangent = np.stack([-n[:, 1], n[:, 0]], axis=1)
    return np.asarray(contact.rn)[:, None] * n + np.asarray(contact.rt)[:, None] * tangent


def _penalty_resolution(law, n_pairs, extent):
    """Round-off resolution of a tool's penalty force (N/mm): each pair's force is resolved to eps_n x
    one ulp of its position along the drive (``extent``, mm) only (eps_n = 1e12: 5.6e-5 N/mm at 0.395
    mm), summed over the tool's ``n_pairs`` pairs; Newton may stop at that floor
    (jaxfric.numerics.newton, NewtonOptions.roundoff)."""
    return np.finfo(float).eps * float(getattr(law, "eps_n", 0.0)) * n_pairs * extent


def _check_contact(scene, res, equilibrium_rtol=1e-6):
    """Physical checks of the last converged state, valid for every scene and law.

    - R_N >= 0, Coulomb |R_T| <= mu R_N on every pair (mu of the tool in the state's phase);
    - penalty law: -g = R_N / eps_n on every closed pair (penalty), g >= -target_gap (AL);
    - every force-driven tool carries its prescribed force: e_q . (sum of its pair forces) = P;
    - equilibrium of the sheet: support reactions (prescribed dofs) + contact forces = 0.
    """
    model, state = scene.model, res.final
    c = state.contact
    rn, rt, gap, status = (np.asarray(a) for a in (c.rn, c.rt, c.gap, c.status))
    f = _pair_forces(c)
    scale = max(float(np.abs(f).sum()), 1e-12)
    phase = int(state.phase)
    mu = np.concatenate([np.full(len(t.candidates), float(np.asarray(t.mu)[phase])) for t in model.tools])
    assert np.all(rn >= -1e-12 * scale)
    assert np.all(np.abs(rt) <= mu * rn * (1 + 1e-9) + 1e-12 * scale)
    closed = status > 0
    law = model.contact
    if isinstance(law, Penalty):   # and StiffPenalty, the same law from another start
        np.testing.assert_allclose(-gap[closed], rn[closed] / float(law.eps_n), rtol=1e-3, atol=1e-15)
    elif isinstance(law, AugmentedLagrangian):
        assert np.all(gap[closed] >= -float(law.target_gap) * (1 + 1e-6))
    sizes = np.cumsum([0] + [len(t.candidates) for t in model.tools])
    tau = float(np.clip(float(state.time) - phase, 0.0, 1.0))
    for k, tool in enumerate(model.tools):
        resultant = np.asarray(tool.drive) @ f[sizes[k]:sizes[k + 1]].sum(axis=0)
        np.testing.assert_allclose(float(np.asarray(c.force)[k]), resultant, rtol=1e-9, atol=1e-9 * scale)
        control = tool.controls[phase]
        if isinstance(control, Force):
            p0 = float(np.asarray(c.f_start)[k]) if control.start is None else float(control.start)
            prescribed = p0 + tau * (float(control.end) - p0)
            coords = np.asarray(model.mesh.nodes) + np.asarray(state.u)
            ulp_force = _penalty_resolution(law, len(tool.candidates),
                                            float(np.max(np.abs(coords @ np.asarray(tool.drive)))))
            assert abs(resultant - prescribed) <= 1e-8 * max(prescribed, 1.0) + 1e-9 * scale + ulp_force, (
                tool.name, resultant, prescribed, ulp_force)
    mask = constraint_masks(model.mesh.n_nodes, model.phases)[phase].reshape(-1, 2)
    support = np.where(mask, np.asarray(reactions(model, state)), 0.0).sum(axis=0)
    imbalance = support + f.sum(axis=0)
    # The closed pairs' penalty forces are resolved to eps_n x one ulp of the coordinates only (eps_n =
    # 1e12 on the Nine, 50 mm long: 7e-3 N/mm per pair), where Newton may stop.
    coords = np.asarray(model.mesh.nodes) + np.asarray(state.u)
    floor = _penalty_resolution(law, int(np.sum(closed)), float(np.max(np.abs(coords))))
    # A last step taken by the stabilised attempt is the damped problem's solution (StepControl,
    # ``stabilize``): the sheet's imbalance is then the damper's resultant, eta times the sum of u - u_n
    # over the free dofs, which the step's damping energy E = eta |u - u_n|^2 bounds by sqrt(n eta E) in
    # each direction (Cauchy-Schwarz over its n free dofs; eta the larger of the two dampers).
    eta = STABILIZE_RISE * scene.control.stabilize * float(model.material.E)
    damper = np.sqrt((~mask).sum(axis=0) * eta * float(res.history["damping_energy"][-1]))
    assert np.all(np.abs(imbalance) <= equilibrium_rtol * max(scale, np.abs(support).sum()) + floor + damper), \
        (imbalance, scale, floor, damper)


def _check_flat_die(scene, res, slides):
    """The flat die (const_force): force balance of the die at every step (P = F_clamp t during clamp,
    F_clamp during draw), Coulomb and x-equilibrium of the strip (the only x forces are the pull of DC
    and friction: drawing force = |sum R_T|) at every step, penetration bounds, and with ``slides``
    global sliding at the end (drawing force = mu P, every pair slipping)."""
    h, cfg = res.history, scene.config
    F, mu = cfg.F_clamp, cfg.mu
    assert res.converged, res.message
    P = F * np.clip(h["time"], 0.0, 1.0)
    assert np.max(np.abs(h["clamping_force"] - P)) <= 1e-8 * F
    assert np.all(h["sum_ft"] <= h["mu_sum_fn"] * (1 + 1e-9) + 1e-12 * F)
    assert np.max(np.abs(h["drawing_force"] - h["sum_ft"])) <= 1e-6 * F
    assert np.all(h["drawing_force"] <= mu * F * (1 + 1e-8) + 1e-9 * F)
    if isinstance(scene.model.contact, Penalty):   # and StiffPenalty (eps_n = 1e9, 1e12)
        eps_n = cfg.eps_n
        loaded = h["clamping_force"] > 0
        n_pairs = h["n_candidates"][0]
        pen = h["max_penetration"][loaded] * eps_n
        assert np.all(pen >= h["clamping_force"][loaded] / n_pairs * (1 - 1e-3))   # max >= mean
        assert np.all(pen <= h["clamping_force"][loaded] * (1 + 1e-3))             # max <= total
    _check_contact(scene, res)
    if slides:
        np.testing.assert_allclose([h["drawing_force"][-1], h["sum_ft"][-1]], mu * F, rtol=1e-6)
        assert h["n_slip"][-1] == h["n_active"][-1] == h["n_candidates"][-1]


def _flat_die(**overrides):
    return make("flat_die", "const_force", "penalty", {**FAST, **overrides})


# ---- fast: the flat die at its edges ------------------------------------------------------------

@pytest.mark.parametrize("eps_n", [1e2, 1e5, 1e9, 1e12])
def test_flat_die_penalty_range(eps_n):
    """eps_n from 1e2 to 1e12 N/mm with eps_t = eps_n (the largest tangential penalty allowed here):
    converged, with the die's force balance, the penalty law and Coulomb at every step. At 1e12 the
    penetration (5.6e-12 mm) is 1e5 ulps of the coordinates: the law holds to 1e-3 there. 1e12 (above
    100 times the flat die's spec penalty, 1e9) runs the scene's StiffPenalty, whose attempts here all
    succeed with the plain solve."""
    scene = _flat_die(eps_n=eps_n, eps_t=eps_n)
    assert isinstance(scene.model.contact, StiffPenalty) == (eps_n > STIFF_PENALTY_RATIO * 1e9)
    res = _run(f"flat_die eps_n = eps_t = {eps_n:.0e}", scene)
    _check_flat_die(scene, res, slides=eps_n >= 1e5)
    if eps_n == 1e2:  # soft: the die sinks F / (13 eps_n) = 0.038 mm into the strip
        assert 0.03 < res.history["max_penetration"].max() < 0.05


@pytest.mark.parametrize("mu", [pytest.param(0.0, marks=pytest.mark.slow), 0.5, 1.0])
def test_flat_die_friction(mu):
    """mu = 0 (slow: a frictionless tool is another compiled structure): no friction, no drawing force;
    0.5: global sliding at 0.5 P = 25 N/mm; 1.0: the drawn end (P / h = 127 MPa > sigma_y) yields before
    the strip can slide, so the strip slips only partly and the drawing force stays below mu P."""
    scene = _flat_die(mu=mu)
    res = _run(f"flat_die mu = {mu}", scene)
    _check_flat_die(scene, res, slides=mu == 0.5)
    h = res.history
    if mu == 0.0:
        assert np.max(np.abs(h["drawing_force"])) <= 1e-9 * scene.config.F_clamp
        assert np.all(np.asarray(res.final.contact.rt) == 0.0)
    if mu == 1.0:
        assert float(np.max(res.final.material.eqps)) > 1e-5
        assert h["drawing_force"][-1] < 0.95 * scene.config.F_clamp and h["n_slip"][-1] < h["n_active"][-1]
        assert h["drawing_force"][-1] / scene.config.h > scene.config.sigma_y


def test_auglag_target_gap():
    """Augmented Lagrangian with target gap 1e-8 mm (eps_n = eps_t = 1e5): the largest penetration stays
    below 1e-8 mm at every step and the strip slides at mu P. With eps_n = 1e2 the Uzawa updates
    (linear rate ~ eps_n over the strip's stiffness) cannot bring a 0.04 mm penetration to 1e-8 mm in
    20 augmentations: a clean AUGMENTATIONS failure in the first clamp steps."""
    scene = make("flat_die", "const_force", "auglag", {**FAST, "eps_n": 1e5, "eps_t": 1e5, "target_gap": 1e-8})
    res = _run("flat_die auglag target 1e-8, eps_n = eps_t = 1e5", scene)
    _check_flat_die(scene, res, slides=True)
    h = res.history
    assert h["max_penetration"].max() <= 1e-8 * (1 + 1e-9) and h["augmentations"].sum() > 0

    soft = make("flat_die", "const_force", "auglag", {**FAST, "eps_n": 1e2, "target_gap": 1e-8})
    res = _run("flat_die auglag target 1e-8, eps_n = 1e2", soft)
    assert res.code == Result.AUGMENTATIONS and "phase 'clamp'" in res.message
    assert res.history["max_penetration"].max() <= 1e-8 * (1 + 1e-9)


def test_two_runs_are_identical():
    """Two runs from two freshly built scenes: every history column and every array of the final state
    agree to 1e-12 (relative to the column's magnitude; in practice bit for bit)."""
    a = _run("flat_die determinism, run 1", _flat_die(mu=0.5))
    b = _run("flat_die determinism, run 2", _flat_die(mu=0.5))
    assert a.history.keys() == b.history.keys()
    for key in a.history:
        if key == "wall_s" or a.history[key].dtype.kind not in "fiu":
            continue
        x, y = a.history[key].astype(float), b.history[key].astype(float)
        assert x.shape == y.shape and np.all(np.abs(x - y) <= 1e-12 * max(1.0, np.abs(x).max())), key
    for x, y in zip(jax.tree_util.tree_leaves(a.final), jax.tree_util.tree_leaves(b.final)):
        x, y = np.asarray(x, float), np.asarray(y, float)
        assert np.all(np.abs(x - y) <= 1e-12 * max(1.0, np.abs(x).max()))


def test_failed_steps_are_cut_and_recorded():
    """F_clamp = 5000 N/mm (100x the spec; nominal clamp steps of 500 N/mm): some steps fail, are
    halved and succeed; the run completes with its cuts in history["cutbacks"] (checked against the
    recorded increments in _run) and balances the die force at every step."""
    scene = _flat_die(F_clamp=5000.0)
    res = _run("flat_die F_clamp = 5000 (cuts)", scene)
    assert res.converged and res.history["cutbacks"].sum() >= 1
    _check_flat_die(scene, res, slides=False)


def test_cut_limit_stops_the_run_cleanly():
    """F_clamp = 1e6 N/mm (nominal clamp steps of 1e5 N/mm, a pressure of 2e5 MPa at the end): near
    6000 N/mm even nominal / 2**10 = 98 N/mm steps do not converge: the run stops after cutting its last
    step down to nominal / 2**max_cuts and through the stabilised attempts, every earlier step converged
    and kept. With F-bar elements (the flat die's default). Where and how the last attempts fail depends
    on Newton's starts, so either code is a clean stop (measured: the iteration limit at 20,819 N/mm,
    121 steps taken only by the stabilised attempts' damper from 5864 N/mm on, where the run stops
    without it; with every step predicted and no damper, an inverted element at 7153 N/mm)."""
    scene = _flat_die(F_clamp=1e6, element="fbar")
    res = _run("flat_die F_clamp = 1e6 (cut limit)", scene)
    assert not res.converged and res.code in (Result.INVERTED_ELEMENT, Result.MAX_ITERATIONS)
    assert "phase 'clamp'" in res.message and "reduce the nominal step" in res.message
    h = res.history
    np.testing.assert_allclose(h["clamping_force"], 1e6 * h["time"], rtol=1e-8, atol=1e-6)


def test_nonfinite_first_step():
    """F_clamp = 1e300 N/mm: the residual of the first attempt overflows; after max_cuts cuts the run
    stops with NONFINITE at step 0, keeping the (finite) initial state."""
    scene = _flat_die(F_clamp=1e300)
    res = _run("flat_die F_clamp = 1e300 (non-finite)", scene)
    assert res.code == Result.NONFINITE and len(res.history["time"]) == 1
    assert "NaN/Inf" in res.message


def test_nonfinite_mid_run():
    """The draw pulls DC by 4e297 mm (U_draw, U_fine and the increments of the fast case times 2**996,
    so the schedule is bit-identical and the compiled run is reused): the clamp converges, the first
    draw step overflows, and the run stops with NONFINITE at the end of the clamp (step 10, t = 1),
    every kept row finite.

    The fast case's observe is passed: its U_draw only scales the drawing_displacement column, and a
    scene observe with U_draw = 4e297 would need its own compilation."""
    k = 2.0**996
    scene = _flat_die(U_draw=0.006 * k, U_fine=0.0025 * k, dU_fine=2.5e-5 * k, dU=1e-4 * k)
    base = _flat_die()
    assert scene.model.phases[1].increments == base.model.phases[1].increments
    res = _run("flat_die draw of 4e297 mm (non-finite mid-run)", scene, observe=base.observe)
    h = res.history
    assert res.code == Result.NONFINITE and "NaN/Inf" in res.message
    assert len(h["time"]) == 11 and h["time"][-1] == 1.0 and res.message.startswith("stopped after step 10 ")
    assert 1.0 < float(res.simulation.failed_time) < 1.0 + 1e-5
    np.testing.assert_allclose(h["clamping_force"], 50.0 * h["time"], rtol=1e-8, atol=1e-10)


@pytest.mark.slow  # 100 s, 55 of them compiling the bead scene
def test_last_attempt_without_line_search():
    """Bead th045_mu000 with the augmented Lagrangian, wound to 12 deg and drawn 0.1 mm. At some winding
    steps every full Newton step raises the residual a little, so the line search backtracks and Newton
    does not converge in 25 iterations at any length down to nominal / 2**max_cuts. The controller's
    last attempt, without the line search, converges: the run completes, those steps recording
    max_cuts + 1 cuts (max_cuts + 2 where the step's first attempt, from the secant prediction, was
    retried from the converged state at its length). Where they fall depends on the step sequence (a
    front of clamp pairs switching between stick and slip, in wind and in draw, and round-off: XLA's
    optimisation level moves them), so the test asserts that they exist, not where."""
    scene = make("bead", "th045_mu000", "auglag", {"theta": 12.0, "s_draw": 0.1})
    res = _run("bead auglag to 12 deg (plain Newton at the floor)", scene)
    assert res.converged, res.message
    h = res.history
    assert scene.control.max_cuts + 1 <= h["cutbacks"].max() <= scene.control.max_cuts + 2


# ---- slow: load steps, meshes, rotations ----------------------------------------------------------

@pytest.mark.slow
@pytest.mark.parametrize("factor", [10.0, 0.1], ids=["x10", "x0.1"])
def test_flat_die_load_step(factor):
    """Nominal increments 10x larger (dU_fine 2.5e-4, dU 1e-3 mm, 1 clamp step) and 10x smaller
    (2.5e-6, 1e-5 mm, 100 clamp steps) than the spec's: converged, same physics, global sliding."""
    scene = _flat_die(dU_fine=2.5e-5 * factor, dU=1e-4 * factor, n_clamp=max(1, round(10 / factor)))
    res = _run(f"flat_die load step x{factor:g}", scene)
    _check_flat_die(scene, res, slides=True)


@pytest.mark.slow
def test_flat_die_fine_mesh():
    """12 elements through the half thickness (48 x 12, elements 0.1 x 0.033 mm) at the spec's 1e9
    penalty: converged, same physics, global sliding. (1 element through: the fast cases.)"""
    scene = _flat_die(mesh="48x12")
    res = _run("flat_die mesh 48x12", scene)
    _check_flat_die(scene, res, slides=True)


def _rotated(model, degrees):
    """``model`` turned rigidly by ``degrees`` counter-clockwise about the origin: mesh, tools (their
    primitives and drives), and prescribed motions. 90 degrees is exact (a permutation of the
    coordinates with a sign) and turns a componentwise condition on x into one on y; other angles need
    conditions on whole nodes."""
    if degrees == 90.0:
        Q, angle = np.array([[0.0, -1.0], [1.0, 0.0]]), 0.5 * math.pi
    else:
        angle = math.radians(degrees)
        Q = np.array([[math.cos(angle), -math.sin(angle)], [math.sin(angle), math.cos(angle)]])

    def rot(v):
        return Q @ np.asarray(v, np.float64)

    def motion(m):
        if isinstance(m, jf.Ramp):
            return jf.Ramp(rot(m.start), rot(m.end))
        assert isinstance(m, jf.RigidMotion), type(m)  # rotations about a pivot commute in 2D
        return jf.RigidMotion(rot(m.pivot), m.angle_start, m.angle_end, rot(m.shift_start), rot(m.shift_end))

    def bc(b):
        if b.components != (0, 1):
            assert degrees == 90.0, "a componentwise condition turns into one only at 90 degrees"
        components = (0, 1) if b.components == (0, 1) else tuple(1 - c for c in b.components)
        return jf.DirichletBC(b.nodes, components, motion(b.motion))

    def primitive(p):
        if isinstance(p, Segment):
            return Segment(rot(p.start), rot(p.end))
        return Arc(rot(p.centre), p.radius, p.angle_start + angle, p.angle_end + angle, p.concave)

    mesh = dataclasses.replace(model.mesh, nodes=jnp.asarray(np.asarray(model.mesh.nodes) @ Q.T))
    phases = tuple(jf.Phase(p.name, [bc(b) for b in p.bcs], increments=p.increments) for p in model.phases)
    tools = tuple(RigidTool(t.name, Tool(tuple(primitive(p) for p in t.geometry.primitives), t.geometry.normal_side,
                                         t.geometry.d_capture),
                            rot(t.drive), t.candidates, t.controls, t.mu if t.frictional else 0.0)
                  for t in model.tools)
    # Every other field of the model (the element's points through the thickness, its order, the enhanced
    # update, ...) as it is: the turned run is the same discretisation.
    return dataclasses.replace(model, mesh=mesh, phases=phases, tools=tools), Q


def _on_accepted_steps(case, scene):
    """``scene`` whose nominal steps are the accepted steps of its adaptive run, with twice its Newton
    iteration limit: a run and its turned copy then take the same steps, where a step that converges in
    exactly the growth rule's or the iteration limit's count of iterations could otherwise take one more
    when turned and part their load paths."""
    h = _run(f"{case}, adaptive", scene).history
    phases = with_steps(scene.model.phases, h["time"][1:], h["phase"][1:])
    newton = dataclasses.replace(scene.newton, max_iterations=2 * scene.newton.max_iterations)
    return dataclasses.replace(scene, model=dataclasses.replace(scene.model, phases=phases), newton=newton)


def _assert_rotation_invariant(case, scene, degrees, rtol, reaction_rtol=None):
    a = _run(f"{case}, reference", scene)
    turned, Q = _rotated(scene.model, degrees)
    b = _run(f"{case}, turned {degrees:g} deg", dataclasses.replace(scene, model=turned))
    assert a.converged and b.converged, (a.message, b.message)
    assert len(a.history["time"]) == len(b.history["time"]) and np.all(a.history["time"] == b.history["time"]), \
        "the turned run took other steps (see test_rotation_invariance_nine)"
    fa, fb = a.final, b.final
    force = float(np.abs(np.asarray(fa.contact.rn)).max())
    disp = float(np.abs(np.asarray(fa.u)).max())
    np.testing.assert_allclose(np.asarray(fb.u), np.asarray(fa.u) @ Q.T, rtol=0, atol=rtol * disp)
    for name in ("rn", "rt"):
        np.testing.assert_allclose(getattr(fb.contact, name), getattr(fa.contact, name), rtol=0, atol=rtol * force)
    np.testing.assert_allclose(fb.contact.q, fa.contact.q, rtol=0, atol=rtol * max(disp, 1e-3))
    eqps = max(float(np.max(fa.material.eqps)), 1e-3)
    np.testing.assert_allclose(fb.material.eqps, fa.material.eqps, rtol=0, atol=rtol * eqps)
    ra, rb = np.asarray(reactions(scene.model, fa)), np.asarray(reactions(turned, fb))
    np.testing.assert_allclose(rb, ra @ Q.T, rtol=0, atol=(reaction_rtol or rtol) * np.abs(ra).max())
    np.testing.assert_allclose(b.history["clamping_force"], a.history["clamping_force"], rtol=0,
                               atol=rtol * np.abs(a.history["clamping_force"]).max())
    np.testing.assert_array_equal(b.history["n_active"], a.history["n_active"])


@pytest.mark.slow
def test_rotation_invariance_flat_die():
    """The flat die (mu = 1: friction and plasticity) turned by exactly 90 degrees, sheet, die, drive,
    symmetry condition and pull together: displacements (turned back), contact forces, die position,
    plastic strains and reactions agree to 1e-9 of their magnitude (measured 2e-12 to 1e-13). Not to
    round-off: each run stops Newton at its own iterate below the residual tolerance (rtol 1e-8).
    (Arbitrary angles for a frictional contact alone: tests/test_contact.py, capstan at 0.7 rad.)"""
    _assert_rotation_invariant("flat_die mu = 1", _flat_die(mu=1.0), 90.0, 1e-9)


@pytest.mark.slow
def test_rotation_invariance_nine():
    """The Nine scene with its spec free entry (entry_guide = False: every prescribed node is held in
    both directions, so any angle is a valid scene), B pushed 3 mm and the strip drawn 1 mm in 0.1 mm
    steps, turned by 37 degrees, both on the accepted steps of the adaptive run: the same step sequence
    and the same agreement, to 1e-9. Measured: 41 steps, 2 cuts and 622 Newton iterations, turned and
    not."""
    scene = make("nine", "mu017", "penalty", {**NINE, "entry_guide": False, "dq_clamp": 0.1, "dU": 0.1})
    _assert_rotation_invariant("nine free entry", _on_accepted_steps("nine free entry", scene), 37.0, 1e-9)


@pytest.mark.slow
@pytest.mark.parametrize("name", ["bead", "blankholder"])
def test_rotation_invariance_bead_and_blankholder(name):
    """The bead (th090_mu017 on BEAD: the jaw's rigid motion, the clamp dies, the roller) and the
    blankholder (shape1 on BLANK with mu = 0.15: the force-driven lower tool, both ends pulled), with
    exact contact, turned by 37 degrees (their prescribed motions hold whole nodes, so any angle is a
    valid scene): the same step sequence and agreement to 1e-9 of each quantity's magnitude, as for the
    flat die and the Nine, the blankholder's reactions to 1e-8 (measured 2.6e-9: a reaction is a
    residual, and Newton stops below 1e-8 of the force scale).

    The bead runs on the accepted steps of its adaptive run: its wind is cut down to 1/64 of the nominal
    increment, and turned by 37 degrees one of those steps takes an iteration more, so the controller
    grows the increment later and the load paths part (by the time discretisation, not by the turn)."""
    if name == "bead":
        scene = _on_accepted_steps("bead", make("bead", "th090_mu017", "lcp_ssn", BEAD))
        _assert_rotation_invariant(name, scene, 37.0, 1e-9)
    else:
        scene = make("blankholder", "shape1", "lcp_ssn", {**BLANK, "mu": 0.15})
        _assert_rotation_invariant(name, scene, 37.0, 1e-9, reaction_rtol=1e-8)


# ---- slow: the other scenes at their edges -------------------------------------------------------

# Nominal increments 10 times the spec's on each scene's short run (the spec: dq_clamp = dU = 0.1 mm on
# the Nine; dtheta = 0.5 deg, ds = 0.05 mm and 10 clamp steps on the bead; ds_close = 0.05 mm, 10 lock
# steps and dU = 0.1 mm on the blankholder), with strokes long enough for two nominal steps.
LOAD_STEP_X10 = {
    "nine": ("mu017", {**NINE, "dq_clamp": 1.0, "dU": 1.0, "U_draw": 2.0}),
    "bead": ("th090_mu017", {**BEAD, "dtheta": 5.0, "ds": 0.5, "s_draw": 1.0, "n_clamp": 1}),
    "blankholder": ("shape1", {**BLANK, "ds_close": 0.5, "n_lock": 1, "dU": 1.0, "U_pull": 2.0}),
}


@pytest.mark.slow
@pytest.mark.parametrize("name", list(LOAD_STEP_X10))
def test_load_step_x10(name):
    """Each scene with nominal increments 10 times the spec's: converged (the controller cuts where it
    must), with the contact checks, at the end of its stroke. (The flat die: test_flat_die_load_step.)"""
    variant, overrides = LOAD_STEP_X10[name]
    scene = make(name, variant, "penalty", overrides)
    res = _run(f"{name} load step x10", scene)
    assert res.converged, res.message
    _check_contact(scene, res)
    stroke = {"nine": "U_draw", "bead": "s_draw", "blankholder": "U_pull"}[name]
    assert res.history["drawing_displacement"][-1] == pytest.approx(getattr(scene.config, stroke))


NINE_CASES = {
    "mu=0.5": {"mu": 0.5}, "mu=1.0": {"mu": 1.0},
    "t/R1=0.02": {"t": 0.11}, "t/R1=0.5": {"t": 2.75},
    "eps_n=1e2": {"eps_n": 1e2}, "eps_n=1e9": {"eps_n": 1e9}, "eps_n=eps_t=1e12": {"eps_n": 1e12, "eps_t": 1e12},
    "full clearance": {"stroke": 11.0, "dq_clamp": 11.0 / 6},
    "ny=1": {"mesh": "30x1"}, "ny=12": {"mesh": "30x12"},
}


@pytest.mark.slow
@pytest.mark.parametrize("case", list(NINE_CASES))
def test_nine_edges(case):
    """Nine (30 x 2 unless noted, B pushed 3 mm in 6 steps, drawn 1 mm in 4): converged with the contact
    checks (Coulomb, penalty law, equilibrium of the strip), B at its stroke, the strip pulled (drawing
    force > 0). Full clearance: B pushed 2 R1 = 11 mm, as in the spec (its gap to A and C is then
    sqrt(L1^2 + t^2) - 2 R1 = 1.04 t).

    eps_n = 1e9 and 1e12 (5e3 and 5e6 E) run the scene's StiffPenalty: a failed attempt is solved again
    from the compliant semismooth solve, the penalty law's solution (the plain law fills the history
    buffer in the clamp, its pair at B 2-cycling between open and a spurious force of 1e4 N/mm).

    t/R1 = 0.02 (t = 0.11 mm) runs the scene's StiffPenalty at the spec's penalty (its threshold scales
    with t^3, :func:`jaxfric.scenes._common.stiff_penalty`; the plain law stopped in clamp).
    """
    scene = make("nine", "mu017", "penalty", {**NINE, **NINE_CASES[case]})
    res = _run(f"nine {case}", scene)
    assert res.converged, res.message
    _check_contact(scene, res)
    h = res.history
    clamp = h["phase_name"] == "clamp"
    assert h["tool_position"][clamp][-1] == pytest.approx(scene.config.stroke)
    assert h["drawing_displacement"][-1] == pytest.approx(scene.config.U_draw)
    assert h["clamping_force"][-1] > 0 and h["drawing_force"][-1] > 0
    if case == "full clearance":
        assert h["max_penetration"].max() < 0.01 * scene.config.t


BEAD_CASES = {
    "mu_roller=0.5": {"mu_roller": 0.5}, "mu_roller=1.0": {"mu_roller": 1.0},
    "mu_clamp=mu_roller=0.5": {"mu_clamp": 0.5, "mu_roller": 0.5},
    "mu_clamp=mu_roller=1.0": {"mu_clamp": 1.0, "mu_roller": 1.0},
    "t/R_r=0.02": {"t": 0.7, "R_r": 35.0, "mesh": "100x4"}, "t/R_r=0.5": {"t": 2.5},
    "foil t=0.1": {"t": 0.1},
    "eps_n=1e2": {"eps_n": 1e2}, "eps_n=1e9": {"eps_n": 1e9}, "eps_n=1e12": {"eps_n": 1e12},
    "ny=1": {"mesh": "100x1"}, "ny=12": {"mesh": "100x12"},
}


@pytest.mark.slow
@pytest.mark.parametrize("case", list(BEAD_CASES))
def test_bead_edges(case):
    """Bead th090_mu017 (100 x 2 unless noted, frictionless clamp dies unless noted, wound 10 deg, drawn
    0.5 mm): converged with the contact checks, die_up at F_clamp from the end of clamp on, the jaw at
    theta and s_draw.

    t/R_r = 0.02 is the industrial proportion, a 0.7 mm strip over a 35 mm roller, on the spec's 4
    layers (its steps' predicted attempts fail and are retried from the converged state,
    :func:`jaxfric.loadpath.controller.retry_from_converged`).

    The foil, t = 0.1 mm over the 5 mm roller between frictionless clamp dies, has no back tension: it
    is held along the strip by its bending alone (E t^3 / 12 = 17 N mm). Its penalty is stiff against that
    bending, so it runs the scene's StiffPenalty (:func:`jaxfric.scenes._common.stiff_penalty`), as eps_n =
    1e9 and 1e12 do (the plain law filled the buffer in wind): failed attempts solved again from the
    compliant semismooth solve. mu_clamp = mu_roller = 1.0 (where the slipping pairs at the clamp's exit
    switch together between stick and slip) takes some steps only with the step controller's damper
    (:class:`jaxfric.loadpath.controller.StepControl`, ``stabilize``).
    """
    scene = make("bead", "th090_mu017", "penalty", {**BEAD, **BEAD_CASES[case]})
    res = _run(f"bead {case}", scene)
    assert res.converged, res.message
    _check_contact(scene, res)
    h = res.history
    loaded = h["time"] >= 1.0
    np.testing.assert_allclose(h["clamping_force"][loaded], scene.config.F_clamp, rtol=1e-8)
    assert h["theta_deg"][-1] == pytest.approx(scene.config.theta)
    assert h["drawing_displacement"][-1] == pytest.approx(scene.config.s_draw)


BLANK_CASES = {
    "full clearance": {}, "t/R=0.02": {"t": 0.12}, "t/R=0.5": {"t": 3.0},
    "eps_n=1e2": {"eps_n": 1e2}, "eps_n=1e9": {"eps_n": 1e9}, "eps_n=1e12": {"eps_n": 1e12},
    "ny=1": {"ny": 1}, "ny=12": {"ny": 12},
    "mu=0.15": {"mu": 0.15}, "mu=0.5": {"mu": 0.5}, "mu=1.0": {"mu": 1.0},
}


@pytest.mark.slow
@pytest.mark.parametrize("case", list(BLANK_CASES))
def test_blankholder_edges(case):
    """Blankholder shape 1 (element length 1 mm, frictionless unless noted): the lower tool closes by
    H = 6 mm (the bead at full clearance: the lands then hold the sheet between them), is locked at
    F_clamp and holds it while the sheet is pulled 1 mm. Checks: contact physics, s = H at the end of
    close, F_clamp from the end of lock on.

    eps_n = 1e9 and 1e12 run the scene's StiffPenalty (failed attempts solved again from the
    compliant semismooth solve; the plain law filled the buffer in close), and so does t/R = 0.02
    (t = 0.12 mm) at the spec's penalty: the threshold scales with the sheet's bending stiffness, t^3
    (:func:`jaxfric.scenes._common.stiff_penalty`; the plain law filled the buffer in close, 500 rows at
    t = 0.67).
    """
    scene = make("blankholder", "shape1", "penalty", {**BLANK, **BLANK_CASES[case]})
    res = _run(f"blankholder {case}", scene)
    assert res.converged, res.message
    _check_contact(scene, res)
    h = res.history
    assert h["tool_position"][h["phase_name"] == "close"][-1] == pytest.approx(scene.config.H)
    coords = np.asarray(scene.model.mesh.nodes) + np.asarray(res.final.u)
    lower = next(t for t in scene.model.tools if t.name == "lower")   # the force-driven tool
    resolution = _penalty_resolution(scene.model.contact, len(lower.candidates),
                                     float(np.max(np.abs(coords))))   # eps_n = 1e12: 4.7e-3 N/mm measured
    np.testing.assert_allclose(h["clamping_force"][h["time"] >= 2.0], scene.config.F_clamp, rtol=1e-8,
                               atol=resolution)
    assert h["drawing_displacement"][-1] == pytest.approx(scene.config.U_pull)


@pytest.mark.slow
def test_penalty_continuation_carries_a_step_that_newton_cannot_take_at_the_stiff_penalty():
    """Bead th090_mu017 at eps_n = 1e12 (1e7 x the spec) with the plain penalty law (not the scene's
    StiffPenalty, which solves a failed attempt again from the compliant semismooth solve): without the
    continuation of StepControl the run stops in 'clamp' (t = 0.375, MAX_ITERATIONS at the smallest increment:
    the roller's first pairs 2-cycle between open and a spurious force); with it the run passes that step and
    goes on in 'clamp' until its history buffer is full (no accepted step records more than max_cuts + 1
    attempts, so no softened stage ends a step here: the continuation changes which attempts follow a failure at
    the smallest increment). The scenes' StiffPenalty finishes this case (test_bead_edges[eps_n=1e12]). Both
    runs without the stabilised attempts (StepControl.stabilize = 0), whose damper would carry the plain run on
    in 'clamp' too."""
    scene = make("bead", "th090_mu017", "penalty", {**BEAD, "eps_n": 1e12, "stabilize": 0.0})
    law = scene.model.contact   # the scene's StiffPenalty: the plain law here
    scene = dataclasses.replace(scene, model=dataclasses.replace(scene.model, contact=Penalty(law.eps_n, law.eps_t)))
    plain = _run("bead eps_n=1e12, plain Penalty, no continuation", scene,
                 control=dataclasses.replace(scene.control, continuation=False))
    assert not plain.converged and plain.code == Result.MAX_ITERATIONS and "(phase 'clamp')" in plain.message
    res = _run("bead eps_n=1e12, plain Penalty", scene)
    h = res.history
    assert float(h["time"][-1]) > float(plain.history["time"][-1])


# ---- slow: a force-driven tool that loses and regains contact -------------------------------------

@pytest.mark.slow
@pytest.mark.parametrize("law", [Penalty(1e2, 0.0), Penalty(1e12, 0.0), AugmentedLagrangian(1e5, 0.0, target_gap=1e-8)],
                         ids=["penalty 1e2", "penalty 1e12", "auglag 1e-8"])
def test_force_driven_tool_loses_and_regains_contact(law):
    """The cycle of tests/test_contact.py (there at eps_n = 1e9) at the penalty edges and with AL: a
    force-driven die clamps a strip to 50 N/mm, is released to 0, the strip is lowered 0.01 mm away
    from it (the die follows it with zero force), and the die presses again to 50 N/mm. Every step
    converges and balances the die force; the die ends where the strip went; all pairs close again.

    eps_n = 1e12: one ulp of the top coordinate (5.6e-17 mm at y = 0.395) is 5.6e-5 N/mm of contact
    force there, far above the residual tolerance (~1.6e-8 N/mm): Newton's residual test converges there
    only by its round-off floor (NewtonOptions.roundoff; without it the clamp stops with MAX_ITERATIONS),
    and the die balance is checked to that resolution (largest deviation over the history measured 3.2e-5
    and 3.9e-5 N/mm of 50 in two runs)."""
    L, h, force = 6.0, 0.395, 50.0
    mesh = jf.strip_mesh(0.0, L, 0.0, h, 30, 2)
    die = RigidTool("die", Tool.line((-2.0, h), (L + 2.0, h)), drive=(0.0, -1.0), candidates=mesh.top,
                    controls=(Force(force, start=0.0), Force(0.0), Force(0.0, start=0.0), Force(force)), mu=0.0)

    def bottom(v0, v1):
        return jf.DirichletBC(mesh.bottom, components=(1,), motion=jf.Ramp((0, v0), (0, v1)))

    hold = jf.DirichletBC(mesh.right, components=(0,))
    phases = (jf.Phase("clamp", [bottom(0, 0), hold], 5), jf.Phase("release", [bottom(0, 0), hold], 5),
              jf.Phase("drop", [bottom(0, -0.01), hold], 5), jf.Phase("press", [bottom(-0.01, -0.01), hold], 5))
    model = jf.StripModel(mesh, jf.J2Material.elastic(69004.0, 0.3), phases, tools=(die,), contact=law)
    scene = types.SimpleNamespace(model=model, control=jf.StepControl(), observe=jf.default_observe,
                                  newton=jf.NewtonOptions())
    case = {1e2: "penalty 1e2", 1e12: "penalty 1e12"}.get(float(law.eps_n), "auglag 1e-8")
    res = _run(f"die loses/regains contact, {case}", scene)
    assert res.converged, res.message
    _check_contact(scene, res)
    hist = res.history
    t = hist["time"]
    prescribed = np.select([t <= 1, t <= 2, t <= 3], [force * t, force * (2 - t), 0.0], force * (t - 3))
    # The die force to 1e-8, or to the penalty's round-off resolution: 2.7e-3 N/mm at 1e12 (measured
    # 3.2e-5 and 3.9e-5 there).
    ulp_force = _penalty_resolution(law, mesh.top.size, h)
    np.testing.assert_allclose(hist["tool_force"][:, 0], prescribed, rtol=0, atol=1e-8 * force + ulp_force)
    dropped = np.isclose(t, 3.0)
    assert abs(hist["tool_position"][dropped, 0][0] - 0.01) < 1e-6
    assert hist["n_active"][-1] == mesh.top.size
    if isinstance(law, AugmentedLagrangian):
        assert hist["max_penetration"].max() <= 1e-8 * (1 + 1e-9)
