"""Exact complementarity (spec 1.7, 1.8): Lemke's pivoting, the contact LCP, and the refinement of Lemke's
answers on their linear piece.

Lemke's answers are checked against what it did not compute: the conditions of the LCP itself
(``assert_lcp_solution``: w = M z + q >= 0, z >= 0, z.w = 0 relative to each row's scale), the
Signorini-Coulomb conditions on the forces and displacements recovered from it (``law_violation``),
the force balance of force-driven tools, the exact solve on the answer's own piece (``polish``), and
closed forms.

Test problems. ``random_problem`` builds K* = D^1/2 (I + E) D^1/2 with ||E||_2 = 0.2 and one scale d_a
per candidate (shared by its normal and tangential dofs). For two solutions of the incremental
Signorini-Coulomb problem, du K* du = sum dg dR_N + ds dR_T <= mu sum |dR_N| |ds|; in the variables
v = D^1/2 du the left side is >= 0.8 |v|^2 and the right side <= 0.7 mu |v|^2, so the solution
(du_c, p, dq) is unique for every mu <= 1 whatever the scales: any valid answer is the answer. The
LCP multipliers are never compared: they are not unique (open candidates leave lambda+ - lambda- free).

Lemke runs as the package calls it, :func:`jaxfric.contact.lcp.lemke_contact_callback` under ``jit``
(``lemke_jit``): compiled once per shape, the pivoting on the host.
"""

import time
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxfric.contact.alart_curnier import polish
from jaxfric.contact.lcp import ForceDrive, contact_lcp, lemke_contact_callback, lemke_start, recover_solution
from jaxfric.contact.lemke import LemkeStatus, lemke
from jaxfric.contact.status import OPEN, SLIP, STICK, contact_status

AGREE = 1e-8        # relative agreement of two solves of the same problem (spec 1.7: "to solver tolerance")
LAW = 1e-9          # relative violation allowed in the Signorini-Coulomb conditions


# ---------------------------------------------------------------------------------------------
# Problem generators and checks
# ---------------------------------------------------------------------------------------------


def random_problem(seed, n_c, mu, scales=(1e3, 1e3), symmetric=True, open_fraction=0.4):
    """(K*, r*, gap, slip, mu) with a unique solution for mu <= 1 (module docstring).

    Scales (N/mm per mm) are log-uniform per candidate in ``scales``. Gaps (mm): a fraction
    ``open_fraction`` open in [0, 0.02], the others penetrating in [-0.02, 0]. Slips in
    [-0.02, 0.02] mm. r* (N/mm) of the size of the forces those gaps produce.
    """
    rng = np.random.default_rng(seed)
    n = 2 * n_c
    E = rng.standard_normal((n, n))
    if symmetric:
        E = E + E.T
    E *= 0.2 / np.linalg.norm(E, 2)
    d = np.exp(rng.uniform(np.log(scales[0]), np.log(scales[1]), n_c))
    root = np.repeat(np.sqrt(d), 2)
    K = root[:, None] * (np.eye(n) + E) * root[None, :]
    is_open = rng.random(n_c) < open_fraction
    gap = np.where(is_open, rng.uniform(0.0, 0.02, n_c), -rng.uniform(0.0, 0.02, n_c))
    slip = rng.uniform(-0.02, 0.02, n_c)
    r = 0.01 * root**2 * rng.standard_normal(n)
    return K, r, gap, slip, np.full(n_c, float(mu))


def batch(problems):
    """Stack a list of (K, r, gap, slip, mu) tuples along a leading axis."""
    return tuple(jnp.asarray(np.stack(a)) for a in zip(*problems))


def law_violation(du, p, gap, slip, mu, r, force=0.0):
    """Largest relative violation of Signorini and Coulomb (spec 1.4) by (du_c, p).

    Lengths are measured against the largest of |du|, |gap|, |slip|; forces against the largest
    of |p|, |r*| and ``force``.
    """
    du, p, gap, slip, mu, r = (np.asarray(a, np.float64) for a in (du, p, gap, slip, mu, r))
    g, s = gap + du[0::2], slip + du[1::2]
    R_N, R_T = p[0::2], p[1::2]
    L = max(np.abs(du).max(), np.abs(gap).max(), np.abs(slip).max())
    F = max(np.abs(p).max(), np.abs(r).max(), force, 1e-300)
    closed = R_N > LAW * F
    stick = closed & (np.abs(R_T) < (1.0 - 1e-6) * mu * R_N)
    slipping = np.abs(s) > LAW * L
    checks = {
        "gap >= 0": np.max(-g, initial=0.0) / L,
        "R_N >= 0": np.max(-R_N, initial=0.0) / F,
        "g R_N = 0": np.max(np.abs(g * R_N), initial=0.0) / (L * F),
        "|R_T| <= mu R_N": np.max(np.abs(R_T) - mu * R_N, initial=0.0) / F,
        "stick => s = 0": np.max(np.where(stick, np.abs(s), 0.0), initial=0.0) / L,
        "open => R_T = 0": np.max(np.where(closed, 0.0, np.abs(R_T)), initial=0.0) / F,
        "slip => |R_T| = mu R_N": np.max(np.where(slipping, np.abs(np.abs(R_T) - mu * R_N), 0.0),
                                         initial=0.0) / F,
        "R_T opposes s": np.max(np.where(slipping, np.maximum(R_T * np.sign(s), 0.0), 0.0),
                                initial=0.0) / F,
    }
    return max(checks.values()), checks


def rel(a, b, scale):
    return float(np.linalg.norm(np.asarray(a) - np.asarray(b)) / scale)


def assert_lcp_solution(M, q, z, w, tol=1e-10):
    scale = np.abs(M) @ np.abs(z) + np.abs(q)
    assert np.all(z >= 0.0)
    np.testing.assert_allclose(w, M @ z + q, rtol=0, atol=1e-12 * scale.max())
    assert np.all(w >= -tol * scale), f"w min {w.min():.2e}"
    assert np.all(np.abs(z * w) <= tol * scale * np.maximum(z, 1e-300)), f"z.w {np.abs(z * w).max():.2e}"

lemke_jit = jax.jit(lemke_contact_callback)


class Lemke(NamedTuple):
    du_c: np.ndarray   # (2 n_c,) mm
    p: np.ndarray      # (2 n_c,) (R_N, R_T) per candidate, N/mm
    dq: np.ndarray     # (n_q,) mm
    pivots: int
    status: int


def solve_by_lemke(K, r, gap, slip, mu, drive=None, start=None) -> Lemke:
    """The contact problem solved by Lemke as the package solves it (cold start unless ``start``)."""
    du, p, dq, pivots, status = lemke_jit(K, r, gap, slip, mu, drive, start=start)
    return Lemke(np.asarray(du), np.asarray(p), np.asarray(dq), int(pivots), int(status))


def lcp_answer(K, r, gap, slip, mu):
    """Lemke on the contact LCP itself (NumPy), its z checked against the LCP's own conditions; returns
    the (du_c, p) that z gives (:func:`recover_solution`)."""
    M, q = (np.asarray(a) for a in contact_lcp(K, r, gap, slip, mu))
    res = lemke(M, q)
    assert res.status == LemkeStatus.SOLVED
    assert_lcp_solution(M, q, res.z, res.w)
    no_tools = jnp.zeros((2 * len(gap), 0))
    du, p = recover_solution(jnp.asarray(K), r, gap, slip, jnp.asarray(res.z), jnp.zeros(0), no_tools)
    return np.asarray(du), np.asarray(p)


def assert_same_answer(a, b, gap, slip, r, label=""):
    """Two solves give the same du_c and p (relative to the problem's length and force scales)."""
    (du_a, p_a), (du_b, p_b) = a, b
    length = max(np.linalg.norm(du_a), np.linalg.norm(gap), np.linalg.norm(slip))
    force = max(np.linalg.norm(p_a), np.linalg.norm(r))
    e_u, e_p = rel(du_b, du_a, length), rel(p_b, p_a, force)
    assert e_u < AGREE and e_p < AGREE, f"{label}: |du_a - du_b| {e_u:.1e}, |p_a - p_b| {e_p:.1e}"


# ---------------------------------------------------------------------------------------------
# Lemke on general LCPs
# ---------------------------------------------------------------------------------------------


def test_lemke_small_lcp_by_hand():
    # M = [[2, 1], [1, 2]]: both z > 0 solve 2 z1 + z2 = 5, z1 + 2 z2 = 6 -> z = (4/3, 7/3).
    M = np.array([[2.0, 1.0], [1.0, 2.0]])
    res = lemke(M, np.array([-5.0, -6.0]))
    assert res.status == LemkeStatus.SOLVED
    np.testing.assert_allclose(res.z, [4 / 3, 7 / 3], rtol=1e-14)
    np.testing.assert_allclose(res.w, 0.0, atol=1e-14)
    # q = (-1, 2): z = (1/2, 0), w = (0, 5/2).
    res = lemke(M, np.array([-1.0, 2.0]))
    np.testing.assert_allclose(res.z, [0.5, 0.0], atol=1e-15)
    np.testing.assert_allclose(res.w, [0.0, 2.5], atol=1e-15)
    assert res.pivots == 2


def test_lemke_trivial_and_budget():
    M = np.array([[2.0, 1.0], [1.0, 2.0]])
    res = lemke(M, np.array([0.0, 3.0]))
    assert (res.status, res.pivots) == (LemkeStatus.SOLVED, 0)
    np.testing.assert_array_equal(res.z, 0.0)
    assert lemke(M, np.array([-5.0, -6.0]), max_pivots=1).status == LemkeStatus.MAX_PIVOTS


def test_lemke_ray_termination_on_infeasible_lcp():
    # w1 + w2 = -2 for every z: infeasible. M is positive semidefinite, so Lemke must end on a ray.
    M = np.array([[1.0, -1.0], [-1.0, 1.0]])
    res = lemke(M, np.array([-1.0, -1.0]))
    assert res.status == LemkeStatus.RAY


@pytest.mark.parametrize("kind", ["positive_definite", "positive_semidefinite"])
@pytest.mark.parametrize("n", [1, 5, 20, 60])
def test_lemke_random_monotone_lcps(kind, n):
    """M = A A^T (+ skew part), rank n/2 for the semidefinite case; q planted from a complementary
    pair (z*, w*) so that the LCP is feasible. Lemke processes every feasible copositive-plus LCP."""
    rng = np.random.default_rng(n + (kind == "positive_semidefinite") * 100)
    for trial in range(5):
        rank = n if kind == "positive_definite" else max(n // 2, 1)
        A = rng.standard_normal((n, rank))
        S = rng.standard_normal((n, n))
        M = A @ A.T + 0.5 * (S - S.T) + (1e-2 * np.eye(n) if kind == "positive_definite" else 0.0)
        support = rng.random(n) < 0.5
        z_star = np.where(support, rng.uniform(0.1, 1.0, n), 0.0)
        w_star = np.where(support, 0.0, rng.uniform(0.1, 1.0, n))
        q = w_star - M @ z_star
        res = lemke(M, q)
        assert res.status == LemkeStatus.SOLVED, f"trial {trial}: status {res.status}"
        assert_lcp_solution(M, q, res.z, res.w)
        if kind == "positive_definite":  # unique solution
            np.testing.assert_allclose(res.z, z_star, atol=1e-9 * (1 + np.abs(z_star).max()))


def test_lemke_checks_its_answer_and_pivots_again_on_the_scaled_problem(monkeypatch):
    """An end of the pivoting that fails the check on the original data is not reported as solved: the
    problem is pivoted again with D M D, D q (D = |diag M|^-1/2), and if that fails too the status is
    INACCURATE. The inaccurate first run is simulated (a real one needs the blankholder's 768-unknown
    LCP)."""
    import jaxfric.contact.lemke as lemke_module

    M = np.array([[2.0, 1.0], [1.0, 2.0]]) * np.array([1.0, 1e4])[None, :]
    q = np.array([-5.0, -6.0])
    exact = lemke(M, q)
    assert exact.status == LemkeStatus.SOLVED
    calls = []
    real = lemke_module._lemke_path

    def first_run_wrong(M_, q_, *args):
        calls.append(np.array(M_))
        res = real(M_, q_, *args)
        if len(calls) == 1:   # the unscaled run "ends" on a point that is not a solution
            return res._replace(z=res.z + 1.0)
        return res

    monkeypatch.setattr(lemke_module, "_lemke_path", first_run_wrong)
    res = lemke(M, q)
    assert len(calls) == 2 and res.status == LemkeStatus.SOLVED
    d = 1.0 / np.sqrt(np.abs(np.diag(M)))
    np.testing.assert_allclose(calls[1], d[:, None] * M * d[None, :], rtol=1e-15)
    np.testing.assert_allclose(res.z, exact.z, rtol=1e-12)
    assert_lcp_solution(M, q, res.z, res.w)
    assert res.pivots == 2 * exact.pivots

    monkeypatch.setattr(lemke_module, "_lemke_path", lambda *a: real(*a)._replace(z=real(*a).z + 1.0))
    assert lemke(M, q).status == LemkeStatus.INACCURATE

@pytest.mark.parametrize("mu", [0.0, 0.3])
def test_polish_settles_a_point_off_the_solution_piece(mu):
    """polish from a point on the wrong piece (here -2 du_c of the solution, as far off as the last
    basis of a pivoting that ended on a ray may be): its exact solve on that piece is no solution, and
    without refinement it says so; with semismooth Newton started on that piece it returns the
    solution (Lemke's, unique here) and says so."""
    K, r, gap, slip, m = random_problem(4, 12, mu)
    ref = solve_by_lemke(K, r, gap, slip, m)
    assert ref.status == LemkeStatus.SOLVED
    off = -2.0 * ref.du_c
    du, p, dq, iters, solved = polish(K, r, gap, slip, m, off, jnp.zeros(0))
    assert not bool(solved) and int(iters) == 0
    du, p, dq, iters, solved = polish(K, r, gap, slip, m, off, jnp.zeros(0), refine_iter=50)
    assert bool(solved) and 0 < int(iters) <= 50
    worst, checks = law_violation(du, p, gap, slip, m, r)
    assert worst < LAW, checks
    np.testing.assert_allclose(du, ref.du_c, atol=1e-10 * np.abs(ref.du_c).max())
    # Open candidates carry exactly zero force.
    g = gap + np.asarray(du)[0::2]
    assert np.all(np.asarray(p)[0::2][g > 1e-12] == 0.0)


def test_lemke_warm_start_gives_the_cold_solution():
    """Random positive definite LCPs (unique solution): from a random complementary basis Lemke ends on
    the solution of the cold start; from the solution's own basis it needs no pivot."""
    rng = np.random.default_rng(7)
    warm_pivots = []
    for trial in range(40):
        n = int(rng.integers(2, 40))
        A = rng.standard_normal((n, n))
        S = rng.standard_normal((n, n))
        M = A @ A.T + 0.3 * (S - S.T) + 1e-2 * np.eye(n)
        q = rng.standard_normal(n)
        cold = lemke(M, q)
        assert cold.status == LemkeStatus.SOLVED
        for start in (rng.random(n) < 0.5, cold.z > 0.0):
            warm = lemke(M, q, start=start)
            assert warm.status == LemkeStatus.SOLVED, trial
            assert_lcp_solution(M, q, warm.z, warm.w)
            np.testing.assert_allclose(warm.z, cold.z, atol=1e-9 * (1 + np.abs(cold.z).max()))
        assert warm.pivots == 0
        warm_pivots.append(lemke(M, q, start=rng.random(n) < 0.5).pivots)
    # All False is the cold start itself.
    assert lemke(M, q, start=np.zeros(n, bool)).pivots == cold.pivots
    assert np.mean(warm_pivots) > 0  # random guesses do pivot


@pytest.mark.parametrize("mu", [0.0, 0.3])
def test_lemke_start_from_the_solution_forces(mu):
    """The basis guessed from a contact solution's forces (lemke_start) is that solution's: the contact
    LCP then solves with no pivot, and the forces and displacements are the cold start's."""
    K, r, gap, slip, mu_c = random_problem(3, 12, mu)
    cold = solve_by_lemke(K, r, gap, slip, mu_c)
    assert cold.status == LemkeStatus.SOLVED and cold.pivots > 0
    start = lemke_start(cold.p, slip + cold.du_c[1::2], mu_c)
    warm = solve_by_lemke(K, r, gap, slip, mu_c, start=start)
    assert warm.status == LemkeStatus.SOLVED and warm.pivots == 0
    scale = np.abs(cold.p).max()
    np.testing.assert_allclose(warm.p, cold.p, rtol=0, atol=1e-9 * scale)
    np.testing.assert_allclose(warm.du_c, cold.du_c, rtol=0, atol=1e-9 * np.abs(cold.du_c).max())


@pytest.mark.parametrize("mu", [0.0, 0.3])
def test_lemke_warm_start_corrects_the_slip_direction_of_open_candidates(mu):
    """A guess that is the solution's basis except for the slip direction of every open candidate
    (which the forces of an open pair cannot tell): the warm start reads the directions off the
    guess's own solution and ends on the cold start's solution without a pivot."""
    K, r, gap, slip, mu_c = random_problem(5, 12, mu)
    cold = solve_by_lemke(K, r, gap, slip, mu_c)
    assert cold.status == LemkeStatus.SOLVED
    start = np.asarray(lemke_start(cold.p, slip + cold.du_c[1::2], mu_c)).reshape(-1, 3)
    is_open = start[:, 0]
    assert is_open.sum() >= 2 and np.any(np.abs(cold.du_c[1::2][is_open] + slip[is_open]) > 1e-6)
    wrong = start.copy()
    wrong[is_open, 1:] = start[is_open, 1:][:, ::-1]
    M, q = contact_lcp(K, r, gap, slip, mu_c)
    res = lemke(np.asarray(M), np.asarray(q), start=wrong.reshape(-1))
    assert res.status == LemkeStatus.SOLVED and res.pivots == 0
    assert_lcp_solution(np.asarray(M), np.asarray(q), res.z, res.w)
    p = recover_solution(jnp.asarray(K), r, gap, slip, jnp.asarray(res.z), jnp.zeros(0), jnp.zeros((24, 0)))[1]
    np.testing.assert_allclose(p, cold.p, rtol=0, atol=1e-9 * np.abs(cold.p).max())


@pytest.mark.parametrize("mu", [0.0, 0.3, 0.9])
def test_lemke_warm_start_on_contact_lcps(mu):
    """Contact LCPs (M = A K* B, not positive definite: warm runs may end on rays and restart, or fall
    back to the cold start): from random starting bases and from the solution's basis with every slip
    direction reversed, the forces and displacements are those of the cold start."""
    rng = np.random.default_rng(11)
    for seed in range(6):
        K, r, gap, slip, mu_c = random_problem(seed, 15, mu)
        cold = solve_by_lemke(K, r, gap, slip, mu_c)
        assert cold.status == LemkeStatus.SOLVED
        best = np.asarray(lemke_start(cold.p, slip + cold.du_c[1::2], mu_c)).reshape(-1, 3)
        flipped = best[:, [0, 2, 1]] & ~best[:, [1, 2]].all(axis=1, keepdims=True)  # reversed slips
        for start in (rng.random(45) < 0.5, flipped.reshape(-1)):
            warm = solve_by_lemke(K, r, gap, slip, mu_c, start=start)
            assert warm.status == LemkeStatus.SOLVED
            np.testing.assert_allclose(warm.p, cold.p, rtol=0, atol=1e-8 * np.abs(cold.p).max())
            np.testing.assert_allclose(warm.du_c, cold.du_c, rtol=0, atol=1e-8 * np.abs(cold.du_c).max())


def test_lemke_contact_callback_under_jit_and_vmap():
    """Batched, the callback pivots once per problem (``vmap_method="sequential"``) and returns each
    problem's own answer, pivot count and status."""
    problems = [random_problem(s, 4, 0.3) for s in range(3)]
    out = jax.jit(jax.vmap(lemke_contact_callback))(*batch(problems))
    for i, prob in enumerate(problems):
        ref = solve_by_lemke(*prob)
        np.testing.assert_allclose(out[0][i], ref.du_c, rtol=0, atol=1e-12 * np.abs(ref.du_c).max())
        np.testing.assert_allclose(out[1][i], ref.p, rtol=0, atol=1e-12 * np.abs(ref.p).max())
        assert int(out[4][i]) == ref.status == LemkeStatus.SOLVED and int(out[3][i]) == ref.pivots


# ---------------------------------------------------------------------------------------------
# The contact LCP
# ---------------------------------------------------------------------------------------------


def test_contact_lcp_matches_its_definition():
    """M = A K* B, q = A (K* d0 - r*) assembled with explicit loops; w = A p at any z."""
    K, r, gap, slip, mu = random_problem(0, 3, 0.3, symmetric=False)
    mu = np.array([0.0, 0.3, 1.0])
    n_c = 3
    A = np.zeros((3 * n_c, 2 * n_c))
    B = np.zeros((2 * n_c, 3 * n_c))
    for a in range(n_c):
        A[3 * a : 3 * a + 3, 2 * a : 2 * a + 2] = [[1, 0], [mu[a], -1], [mu[a], 1]]
        B[2 * a : 2 * a + 2, 3 * a : 3 * a + 3] = [[1, 0, 0], [0, -1, 1]]
    d0 = -np.column_stack([gap, slip]).ravel()
    M, q = contact_lcp(K, r, gap, slip, mu)
    np.testing.assert_allclose(M, A @ K @ B, rtol=1e-14, atol=1e-12 * np.abs(K).max())
    np.testing.assert_allclose(q, A @ (K @ d0 - r), rtol=1e-14, atol=1e-12 * np.abs(r).max())
    z = np.random.default_rng(1).uniform(0, 0.01, 3 * n_c)
    du, p = recover_solution(jnp.asarray(K), r, gap, slip, jnp.asarray(z), jnp.zeros(0), jnp.zeros((2 * n_c, 0)))
    np.testing.assert_allclose(du, B @ z + d0, atol=1e-15)
    np.testing.assert_allclose(M @ z + q, A @ np.asarray(p), rtol=1e-12, atol=1e-9)


def test_contact_lcp_rejects_bad_input():
    K, r, gap, slip, mu = random_problem(0, 3, 0.3)
    with pytest.raises(ValueError, match="mu"):
        contact_lcp(K, r, gap, slip, -mu)
    with pytest.raises(ValueError, match="r_star"):
        contact_lcp(K, r[:-1], gap, slip, mu)
    with pytest.raises(ValueError, match="force"):
        ForceDrive(coupling=jnp.zeros((6, 2)), force=jnp.zeros(1))

# ---------------------------------------------------------------------------------------------
# Lemke on contact problems: the LCP's conditions and the contact law
# ---------------------------------------------------------------------------------------------

CONDITIONING = {
    # name: scales of the candidates' stiffness, N/mm per mm
    "well": (1e3, 1e3),
    "stiff": (1e9, 1e9),
    "spread_1e3": (1e3, 1e6),
    "spread_1e6": (1e3, 1e9),
}


@pytest.mark.parametrize("mu", [0.0, 0.17, 0.5, 1.0])
@pytest.mark.parametrize("conditioning", list(CONDITIONING))
def test_lemke_solves_contact_problems(mu, conditioning):
    """Lemke's z satisfies the LCP's conditions, the (du_c, p) it gives satisfy Signorini-Coulomb, and the
    package's callback (the LCP built under jit) returns the same answer."""
    problems = [random_problem(100 * k + int(100 * mu), 10, mu, CONDITIONING[conditioning], symmetric=k % 2 == 0,
                               open_fraction=[0.0, 0.3, 0.6, 1.0][k % 4]) for k in range(8)]
    for k, (K, r, gap, slip, m) in enumerate(problems):
        lem = solve_by_lemke(K, r, gap, slip, m)
        assert lem.status == LemkeStatus.SOLVED, f"problem {k}: Lemke status {lem.status}"
        worst, checks = law_violation(lem.du_c, lem.p, gap, slip, m, r)
        assert worst < LAW, f"problem {k}: {checks}"
        assert_same_answer(lcp_answer(K, r, gap, slip, m), (lem.du_c, lem.p), gap, slip, r, f"problem {k}")


def test_degenerate_data_zero_gaps_slips_and_loads():
    """Zero gaps (closed at zero gap), zero slips and zero loads put zeros in q and ties in every
    ratio test. The solution here is du = 0 or close to it; Lemke must find it."""
    for k in range(8):
        K, r, gap, slip, mu = random_problem(500 + k, 10, [0.0, 0.17, 0.5, 1.0][k % 4])
        rng = np.random.default_rng(k)
        gap = np.where(rng.random(10) < 0.6, 0.0, gap)
        slip = np.where(rng.random(10) < 0.6, 0.0, slip)
        r = np.where(rng.random(20) < 0.5, 0.0, r) if k % 3 else np.zeros(20)
        lem = solve_by_lemke(K, r, gap, slip, mu)
        assert lem.status == LemkeStatus.SOLVED
        du, p = lcp_answer(K, r, gap, slip, mu)
        # Absolute scales: with zero data the solution itself may be 0.
        force = 0.02 * np.abs(K).max()
        assert rel(du, lem.du_c, 0.02) < AGREE and rel(p, lem.p, force) < AGREE
        assert law_violation(lem.du_c, lem.p, gap, slip, mu, r, force)[0] < LAW


def test_all_open_gives_the_free_solution():
    """Gaps that stay open: p = 0 and du = K*^-1 r* (the sheet moves freely)."""
    K, _, _, slip, mu = random_problem(11, 10, 0.5)
    du_free = np.random.default_rng(0).uniform(-0.005, 0.005, 20)
    r = K @ du_free
    gap = np.full(10, 0.01)                   # g = 0.01 + du_N > 0
    lem = solve_by_lemke(K, r, gap, slip, mu)
    np.testing.assert_allclose(lem.du_c, du_free, rtol=1e-10, atol=1e-14)
    np.testing.assert_allclose(lem.p, 0.0, atol=1e-10 * np.abs(r).max())
    np.testing.assert_array_equal(packed_status(lem.p, mu), OPEN)


def test_all_closed_in_stick_and_in_slip():
    """All penetrating, no load: every gap closes. With no step slip everything sticks; with a
    large step slip of one sign everything slides and R_T = -mu R_N sign(s)."""
    K, _, _, _, mu = random_problem(12, 10, 0.5)
    r = np.zeros(20)
    gap = np.full(10, -0.01)
    for slip, expected in [(np.zeros(10), STICK), (np.full(10, 0.5), SLIP)]:
        lem = solve_by_lemke(K, r, gap, slip, mu)
        assert lem.status == LemkeStatus.SOLVED
        worst, checks = law_violation(lem.du_c, lem.p, gap, slip, mu, r)
        assert worst < LAW, checks
        np.testing.assert_allclose(gap + lem.du_c[0::2], 0.0, atol=1e-14)
        np.testing.assert_array_equal(packed_status(lem.p, mu), expected)
        if expected == SLIP:
            np.testing.assert_allclose(lem.p[1::2], -mu * lem.p[0::2], rtol=1e-10)
        else:
            np.testing.assert_allclose(slip + lem.du_c[1::2], 0.0, atol=1e-14)


def test_single_candidate_by_hand():
    """K* = k I, r* = 0, g = -0.01, s = 0.02, mu = 0.5: closing needs R_N = 0.01 k; sticking would
    need |R_T| = 0.02 k > mu R_N, so it slides: R_T = -0.005 k, du_T = -0.005, s = 0.015 > 0."""
    k = 2e5
    K, r = k * np.eye(2), np.zeros(2)
    gap, slip, mu = np.array([-0.01]), np.array([0.02]), np.array([0.5])
    lem = solve_by_lemke(K, r, gap, slip, mu)
    np.testing.assert_allclose(lem.du_c, [0.01, -0.005], rtol=1e-13)
    np.testing.assert_allclose(lem.p, [0.01 * k, -0.005 * k], rtol=1e-13)
    # Frictionless: slides freely, R_T = 0 and the whole slip remains.
    lem = solve_by_lemke(K, r, gap, slip, 0 * mu)
    np.testing.assert_allclose(lem.du_c, [0.01, 0.0], atol=1e-15)
    np.testing.assert_allclose(lem.p, [0.01 * k, 0.0], atol=1e-10)


def clamped_strip_stiffness(nx=40, ny=4, length=40.0, thickness=1.0, E=2e5, nu=0.3):
    """K* of a real sheet: plane-strain linear Q4 strip (2x2 Gauss) clamped at x = 0, condensed on
    its bottom nodes (the clamped one excluded), in the frames n = +y, t = (-n_y, n_x) = -x of a
    flat die below it, so (u_N, u_T) = (u_y, -u_x). Shape (2 nx, 2 nx), N/mm per mm.

    Condensed bending stiffness couples neighbouring normals with both signs: K* is far from an
    M-matrix, and on these data the plain active-set iteration cycles on 2 of 16 problems.
    """
    lam, G = E * nu / ((1 + nu) * (1 - 2 * nu)), E / (2 * (1 + nu))
    D = np.array([[lam + 2 * G, lam, 0.0], [lam, lam + 2 * G, 0.0], [0.0, 0.0, G]])
    hx, hy = length / nx, thickness / ny
    xi_a, eta_a = np.array([-1, 1, 1, -1]), np.array([-1, -1, 1, 1])
    Ke = np.zeros((8, 8))
    for xi in (-1 / np.sqrt(3), 1 / np.sqrt(3)):
        for eta in (-1 / np.sqrt(3), 1 / np.sqrt(3)):
            dN = np.stack([xi_a * (1 + eta_a * eta) / (2 * hx), eta_a * (1 + xi_a * xi) / (2 * hy)])
            Bm = np.zeros((3, 8))
            Bm[0, 0::2], Bm[1, 1::2], Bm[2, 0::2], Bm[2, 1::2] = dN[0], dN[1], dN[1], dN[0]
            Ke += Bm.T @ D @ Bm * hx * hy / 4
    node = lambda i, j: i * (ny + 1) + j  # noqa: E731  (column-by-column numbering, spec section 0)
    n_dof = 2 * (nx + 1) * (ny + 1)
    K = np.zeros((n_dof, n_dof))
    for i in range(nx):
        for j in range(ny):
            dofs = np.ravel([[2 * a, 2 * a + 1] for a in (node(i, j), node(i + 1, j), node(i + 1, j + 1),
                                                          node(i, j + 1))])
            K[np.ix_(dofs, dofs)] += Ke
    clamped = np.ravel([[2 * node(0, j), 2 * node(0, j) + 1] for j in range(ny + 1)])
    bottom = np.array([node(i, 0) for i in range(1, nx + 1)])
    c = np.ravel(np.column_stack([2 * bottom + 1, 2 * bottom]))
    f = np.setdiff1d(np.arange(n_dof), np.concatenate([clamped, c]))
    K_star = K[np.ix_(c, c)] - K[np.ix_(c, f)] @ np.linalg.solve(K[np.ix_(f, f)], K[np.ix_(f, c)])
    sign = np.tile([1.0, -1.0], bottom.size)
    return sign[:, None] * K_star * sign[None, :]


@pytest.fixture(scope="module")
def strip():
    return clamped_strip_stiffness()


def test_clamped_strip_on_a_flat_die(strip):
    """Random penetrations, slips and loads on a real condensed sheet stiffness, mu < 1: the LCP's
    conditions and the contact law hold."""
    K = strip
    n_c = K.shape[0] // 2
    for seed in range(16):
        rng = np.random.default_rng(seed)
        gap, slip = rng.uniform(-0.01, 0.01, n_c), rng.uniform(-0.01, 0.01, n_c)
        r = K @ rng.normal(0, 0.01, 2 * n_c) * (seed % 2)
        mu = np.full(n_c, [0.0, 0.17, 0.5][seed % 3])
        lem = solve_by_lemke(K, r, gap, slip, mu)
        assert lem.status == LemkeStatus.SOLVED
        assert_same_answer(lcp_answer(K, r, gap, slip, mu), (lem.du_c, lem.p), gap, slip, r, f"problem {seed}")
        assert law_violation(lem.du_c, lem.p, gap, slip, mu, r)[0] < LAW


def test_global_coulomb_sliding(strip):
    """Strip touching the die, pressed onto it by 10 N/mm per bottom node and slid 0.5 mm: every
    closed pair slides the same way, so the tangential resultant is -mu times the normal one
    (spec section 8)."""
    K = strip
    n_c = K.shape[0] // 2
    gap, slip, mu = np.zeros(n_c), np.full(n_c, 0.5), np.full(n_c, 0.15)
    r = np.zeros(2 * n_c)
    r[0::2] = -10.0
    lem = solve_by_lemke(K, r, gap, slip, mu)
    assert np.sum(lem.p[0::2] > 1e-9) >= n_c // 2, "most of the strip must be in contact"
    np.testing.assert_allclose(lem.p[1::2].sum(), -0.15 * lem.p[0::2].sum(), rtol=1e-10)
    assert np.all(slip + lem.du_c[1::2] > 0.4)


# ---------------------------------------------------------------------------------------------
# Force-driven tools (spec 1.8)
# ---------------------------------------------------------------------------------------------


def random_drive(seed, n_c, n_tools, K):
    """Tool k owns every candidate a with a % (n_tools + 1) == k (the rest belong to a fixed tool);
    its closing direction is within 0.3 rad of the normals; P_k = 0.5 .. 2 % of a stiffness x mm."""
    rng = np.random.default_rng(seed)
    theta = rng.uniform(-0.3, 0.3, n_c)
    C = np.zeros((2 * n_c, n_tools))
    for a in range(n_c):
        k = a % (n_tools + 1)
        if k < n_tools:
            C[2 * a, k], C[2 * a + 1, k] = np.cos(theta[a]), np.sin(theta[a])
    P = rng.uniform(0.5, 2.0, n_tools) * 0.01 * np.mean(np.diag(K))
    return ForceDrive(coupling=jnp.asarray(C), force=jnp.asarray(P))


@pytest.mark.parametrize("n_tools", [1, 2])
def test_force_driven_tool_balance(n_tools):
    """The tool equation sum_a e_q . (R_N n + R_T t) = P holds at Lemke's solution (the tool rows
    eliminated before pivoting), the contact law holds with the gaps moved by the tools, and the exact
    solve on the answer's piece with the tool rows bordered (polish) gives the same du_c, p and dq."""
    for k in range(8):
        mu = [0.0, 0.17, 0.5, 1.0][k % 4]
        K, r, gap, slip, m = random_problem(900 + 10 * n_tools + k, 10, mu, [(1e3, 1e3), (1e3, 1e6)][k % 2],
                                            symmetric=k % 3 > 0)
        drive = random_drive(k, 10, n_tools, K)
        C, P = np.asarray(drive.coupling), np.asarray(drive.force)
        lem = solve_by_lemke(K, r, gap, slip, m, drive)
        assert lem.status == LemkeStatus.SOLVED, f"problem {k}: Lemke status {lem.status}"
        np.testing.assert_allclose(C.T @ lem.p, P, rtol=1e-9, err_msg=f"problem {k}")
        # The gaps seen by the solver include the tool motion.
        gap_q, slip_q = gap - (C[0::2] @ lem.dq), slip - (C[1::2] @ lem.dq)
        assert law_violation(lem.du_c, lem.p, gap_q, slip_q, m, r)[0] < LAW
        du, p, dq, _, solved = polish(K, r, gap, slip, m, lem.du_c, lem.dq, drive)
        assert bool(solved), f"problem {k}"
        assert_same_answer((lem.du_c, lem.p), (du, p), gap, slip, r, f"problem {k}")
        np.testing.assert_allclose(dq, lem.dq, rtol=0, atol=AGREE * max(np.abs(lem.dq).max(), 0.02))


def test_force_driven_single_candidate_by_hand():
    """One frictionless candidate, K* = k I, e_q = n: R_N = P, du_N = P / k, and the tool follows the
    node to close the gap: dq = P / k + g. Touching (g = 0) or starting open (g = 0.3 mm)."""
    k, P = 1e5, 600.0
    K, r = k * np.eye(2), np.zeros(2)
    drive = ForceDrive.single([1.0], [0.0], P)
    for gap in [0.0, 0.3]:
        args = (K, r, np.array([gap]), np.zeros(1), np.zeros(1))
        lem = solve_by_lemke(*args, drive)
        assert lem.status == LemkeStatus.SOLVED
        np.testing.assert_allclose(lem.p, [P, 0.0], rtol=1e-10, atol=1e-10)
        np.testing.assert_allclose(lem.du_c, [P / k, 0.0], rtol=1e-10, atol=1e-15)
        np.testing.assert_allclose(lem.dq, [P / k + gap], rtol=1e-10)
    M, q = contact_lcp(*args, drive)
    assert M.shape == (4, 4) and q.shape == (4,)


# ---------------------------------------------------------------------------------------------
# Status, sizes
# ---------------------------------------------------------------------------------------------


def packed_status(p, mu):
    """The status rule (jaxfric.contact.status) of forces packed as (R_N, R_T) per candidate."""
    p = np.asarray(p).reshape(-1, 2)
    return contact_status(p[:, 0], p[:, 1], mu)


def test_contact_status_thresholds():
    mu = np.array([0.5, 0.5, 0.5, 0.5, 0.0, 0.5])
    p = np.array([1e-9, 0.0,                   # R_N at the open threshold: open
                  1.0, 0.5 * (1 - 1e-6),       # |R_T| = (1 - 1e-6) mu R_N: slip
                  1.0, -0.5 * (1 - 2e-6),      # just inside: stick
                  1.0, 0.5,                    # on the cone: slip
                  1.0, 0.0,                    # closed frictionless: slip
                  -1.0, 0.0])                  # tensile (not a solution, but classified): open
    expected = [OPEN, SLIP, STICK, SLIP,
                SLIP, OPEN]
    np.testing.assert_array_equal(packed_status(p, mu), expected)



@pytest.mark.parametrize("n_c", [30])
def test_larger_problem_and_timing(n_c):
    """A 90-variable LCP: Lemke's answer meets the LCP's conditions and the contact law; timings printed
    for the record (pytest -s)."""
    K, r, gap, slip, mu = random_problem(77, n_c, 0.17, (1e3, 1e5))
    solve_by_lemke(K, r, gap, slip, mu)   # compile
    t0 = time.perf_counter()
    lem = solve_by_lemke(K, r, gap, slip, mu)
    t_lemke = time.perf_counter() - t0
    print(f"n_c = {n_c}: Lemke {lem.pivots} pivots {1e3 * t_lemke:.1f} ms")
    assert lem.status == LemkeStatus.SOLVED
    assert_same_answer(lcp_answer(K, r, gap, slip, mu), (lem.du_c, lem.p), gap, slip, r)
    assert law_violation(lem.du_c, lem.p, gap, slip, mu, r)[0] < LAW
