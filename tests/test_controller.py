"""The step controller's rules (jaxfric.loadpath.controller), each alone and in sequence, without a finite-element
model: attempts' outcomes are made up, so each rule is checked at the case it decides."""

import equinox as eqx
import jax.numpy as jnp
import numpy as np
import pytest

from jaxfric.fem.loading import Phase
from jaxfric.loadpath.controller import (
    ContinuationState,
    Controller,
    Outcome,
    StepControl,
    continuation_rule,
    crawl_count,
    increment_after_acceptance,
    retry_from_converged,
    stop_code,
    unsearched_attempt,
)
from jaxfric.numerics.results import Result

T, F = jnp.array(True), jnp.array(False)


def test_increment_grows_after_easy_steps_up_to_the_nominal_one_and_follows_the_segments():
    control = StepControl(growth=1.5, easy_iterations=6, easy_steps=2)
    # The first easy step counts; the second grows the increment, capped at the nominal one.
    n_easy, grow, dt = increment_after_acceptance(control, T, 0, 3, 0.25, 1.0, 1.0, F)
    assert int(n_easy) == 1 and not bool(grow) and float(dt) == 0.25
    n_easy, grow, dt = increment_after_acceptance(control, T, 1, 6, 0.25, 1.0, 1.0, F)
    assert bool(grow) and float(dt) == 0.375
    assert float(increment_after_acceptance(control, T, 1, 6, 0.9, 1.0, 1.0, F)[2]) == 1.0
    # A hard step resets the count; a step that ends its segment takes the next segment's increment.
    assert int(increment_after_acceptance(control, T, 1, 7, 0.25, 1.0, 1.0, F)[0]) == 0
    assert float(increment_after_acceptance(control, T, 0, 9, 0.25, 1.0, 0.5, T)[2]) == 0.5


def test_retry_from_the_converged_state_for_a_predicted_first_attempt_or_one_at_the_floor():
    # (failed, at_floor, cuts, predicted)
    assert bool(retry_from_converged(T, T, 0, F)) and bool(retry_from_converged(T, F, 0, T))
    assert not bool(retry_from_converged(T, F, 0, F)) and not bool(retry_from_converged(T, T, 3, T))
    assert not bool(retry_from_converged(F, T, 0, T))


@pytest.mark.parametrize("has_line_search", [True, False])
def test_unsearched_attempt_once_after_the_retry_where_a_line_search_exists(has_line_search):
    assert bool(unsearched_attempt(T, F, F, has_line_search)) == has_line_search
    assert not bool(unsearched_attempt(T, T, F, has_line_search))    # the retry comes first
    assert not bool(unsearched_attempt(T, F, T, has_line_search))    # only once
    assert not bool(unsearched_attempt(F, F, F, has_line_search))    # above the floor: halve instead


def _stages(soft, tried=False, staged=False):
    return ContinuationState(soft=jnp.array(soft, jnp.int32), tried=jnp.array(tried), u=jnp.zeros((3, 2)),
                             q=jnp.zeros(1), staged=jnp.array(staged))


def test_continuation_starts_at_the_floor_descends_stage_by_stage_and_ends_on_failure():
    u, q = jnp.ones((3, 2)), jnp.full(1, 2.0)
    n = jnp.array(3, jnp.int32)
    # At the floor, after the retry, with stages available: the first stage (penalties / 10^3).
    new, start, done, held = continuation_rule(_stages(-1), n, T, F, F, F, F, u, q)
    assert bool(start) and int(new.soft) == 3 and not bool(held)
    # Not after the unsearched attempt, nor once it has failed for this step, nor without stages.
    assert not bool(continuation_rule(_stages(-1), n, T, F, T, F, F, u, q)[1])
    assert not bool(continuation_rule(_stages(-1, tried=True), n, T, F, F, F, F, u, q)[1])
    assert not bool(continuation_rule(_stages(-1), jnp.array(0, jnp.int32), T, F, F, F, F, u, q)[1])
    # A converged stage before the last: the next one starts from its solution; it is not a step.
    new, start, done, held = continuation_rule(_stages(2), n, F, F, F, T, F, u, q)
    assert bool(done) and int(new.soft) == 1 and bool(new.staged) and bool(held)
    np.testing.assert_array_equal(new.u, u)
    np.testing.assert_array_equal(new.q, q)
    # A failed stage ends the continuation for the step.
    new, start, done, held = continuation_rule(_stages(2), n, F, F, F, F, F, u, q)
    assert int(new.soft) == -1 and bool(new.tried) and not bool(done) and bool(held)
    # The last stage (true penalties) converged: an accepted step, nothing held.
    new, start, done, held = continuation_rule(_stages(0), n, F, F, F, T, T, u, q)
    assert int(new.soft) == -1 and not bool(done) and not bool(held) and not bool(new.tried)


def test_stop_code_reports_the_last_searched_attempt():
    it, mx = Result.INVERTED_ELEMENT, Result.MAX_ITERATIONS
    assert int(stop_code(T, F, F, T, it, mx)) == it     # the unsearched attempt failed: the one before
    assert int(stop_code(T, F, F, F, it, mx)) == mx
    assert int(stop_code(F, T, F, F, it, mx)) == Result.SUCCESS
    assert int(stop_code(F, F, T, F, it, mx)) == Result.MAX_STEPS
    assert int(stop_code(F, F, F, F, it, mx)) == Result.CONTINUE
    assert int(stop_code(F, F, F, F, it, mx, T)) == Result.STALLED
    assert int(stop_code(F, T, F, F, it, mx, T)) == Result.SUCCESS   # the load path's last step ends it


def _outcome(code, iterations=4, predicted=False):
    return Outcome(jnp.array(code, jnp.int32), jnp.array(iterations, jnp.int32), None, jnp.zeros(3, jnp.int32),
                   jnp.array(1.0 if code != Result.SUCCESS else 0.0), jnp.zeros((3, 2)), jnp.zeros(1),
                   jnp.array(predicted))


def _failing_step(ctrl, cs, t_start=0.0, predicted=False):
    """Attempts of one step that never converges: their targets and whether each ran unsearched.
    ``predicted``: the first attempt starts from the secant prediction (a retry never does)."""
    targets, plain = [], []
    while int(cs.code) == Result.CONTINUE and len(targets) < 20:
        t_try, _ = ctrl.target(cs, t_start)
        targets.append(float(t_try))
        plain.append(bool(cs.plain))
        first = predicted and len(targets) == 1
        cs = ctrl.adapt(cs, t_start, t_try, _outcome(Result.MAX_ITERATIONS, predicted=first), 1)
    return cs, targets, plain


@pytest.mark.parametrize("has_line_search", [True, False])
def test_a_failing_step_is_halved_to_the_floor_then_retried_unsearched_then_stopped(has_line_search):
    """One phase of 4 nominal steps (0.25), max_cuts 2 (floor 0.0625): halve twice; the floor attempt
    already started from the converged state (a cut attempt does), so no retry; then (with a line
    search) once without it; then stop with the failure of the last searched attempt."""
    ctrl = Controller.build((Phase("load", n_steps=4),), StepControl(max_cuts=2), False, has_line_search,
                            jnp.array(0, jnp.int32))
    cs, targets, plain = _failing_step(ctrl, ctrl.init(jnp.zeros((3, 2)), jnp.zeros(1)))
    assert targets == [0.25, 0.125, 0.0625] + ([0.0625] if has_line_search else [])
    assert plain == [False] * 3 + ([True] if has_line_search else [])
    assert int(cs.code) == Result.MAX_ITERATIONS and int(cs.cuts) == len(targets)
    assert float(cs.failed_t) == 0.0625


def test_a_predicted_first_attempt_that_fails_is_retried_at_its_increment_from_the_converged_state():
    """Above the floor too: a first attempt from the secant prediction fails, the same increment from
    the converged state, then halving as before."""
    ctrl = Controller.build((Phase("load", n_steps=4),), StepControl(max_cuts=2), False, True,
                            jnp.array(0, jnp.int32))
    cs, targets, plain = _failing_step(ctrl, ctrl.init(jnp.zeros((3, 2)), jnp.zeros(1)), predicted=True)
    assert targets == [0.25, 0.25, 0.125, 0.0625, 0.0625]
    assert plain == [False] * 4 + [True]
    assert int(cs.code) == Result.MAX_ITERATIONS and int(cs.cuts) == len(targets)


@pytest.mark.parametrize("has_line_search", [True, False])
def test_a_first_attempt_failing_at_the_floor_is_retried_from_the_converged_state(has_line_search):
    """A step whose first attempt (from the secant prediction) is already at the floor increment: the
    same increment once more (``cuts`` > 0: from the converged state), then unsearched, then stop."""
    ctrl = Controller.build((Phase("load", n_steps=4),), StepControl(max_cuts=2), False, has_line_search,
                            jnp.array(0, jnp.int32))
    cs = eqx.tree_at(lambda c: c.dt, ctrl.init(jnp.zeros((3, 2)), jnp.zeros(1)), jnp.array(0.0625))
    cs, targets, plain = _failing_step(ctrl, cs)
    assert targets == [0.0625, 0.0625] + ([0.0625] if has_line_search else [])
    assert plain == [False, False] + ([True] if has_line_search else [])
    assert int(cs.code) == Result.MAX_ITERATIONS


@pytest.mark.parametrize("widenable", [True, False])
def test_an_attempt_ending_outside_the_band_ends_the_program_for_a_wider_band(widenable):
    """An attempt that ends with CONTACT_BAND ends the program with BAND_FULL, the step pending at that
    attempt's increment (the driver widens the band and tries it again); without a band that can grow,
    the failure is cut as any."""
    ctrl = Controller.build((Phase("load", n_steps=4),), StepControl(max_cuts=2), False, True,
                            jnp.array(0, jnp.int32), widenable=widenable)
    cs = ctrl.init(jnp.zeros((3, 2)), jnp.zeros(1))
    cs = ctrl.adapt(cs, 0.0, 0.25, _outcome(Result.CONTACT_BAND, predicted=True), 1)
    if widenable:
        assert int(cs.code) == Result.BAND_FULL and float(cs.dt) == 0.25 and not bool(cs.plain)
        assert int(cs.cuts) == 1 and int(cs.cut_codes) == 1 << Result.CONTACT_BAND
        # Tried again at the wider band, it converges: an accepted step like any.
        cs = ctrl.adapt(eqx.tree_at(lambda c: c.code, cs, jnp.array(Result.CONTINUE, jnp.int32)), 0.0, 0.25,
                        _outcome(Result.SUCCESS), 1)
        assert int(cs.code) == Result.CONTINUE and int(cs.cuts) == 0 and float(cs.dt) == 0.25
    else:   # the predicted attempt's retry from the converged state, then halving
        assert int(cs.code) == Result.CONTINUE and float(cs.dt) == 0.25
        cs = ctrl.adapt(cs, 0.0, 0.25, _outcome(Result.CONTACT_BAND), 1)
        assert int(cs.code) == Result.CONTINUE and float(cs.dt) == 0.125


def test_accepted_steps_reach_the_end_of_the_load_path():
    ctrl = Controller.build((Phase("a", n_steps=2), Phase("b", n_steps=2)), StepControl(), False, True,
                            jnp.array(0, jnp.int32))
    cs = ctrl.init(jnp.zeros((3, 2)), jnp.zeros(1))
    t, row, times = 0.0, 1, []
    while int(cs.code) == Result.CONTINUE:
        t_try, phase = ctrl.target(cs, t)
        times.append((float(t_try), int(phase)))
        cs = ctrl.adapt(cs, t, t_try, _outcome(Result.SUCCESS), row)
        t, row = t_try, row + 1
    assert times == [(0.5, 0), (1.0, 0), (1.5, 1), (2.0, 1)]
    assert int(cs.code) == Result.SUCCESS


def test_continuation_stages_come_between_the_floor_and_the_unsearched_attempt():
    """With two continuation stages: the floor attempt fails; stages 2 and 1 converge (not steps: each
    starts the next); the true-penalty stage fails, which ends the continuation; the unsearched attempt
    fails; the run stops with the code of the last attempt before the stages."""
    ctrl = Controller.build((Phase("load", n_steps=4),), StepControl(max_cuts=2), True, True,
                            jnp.array(2, jnp.int32))
    cs = ctrl.init(jnp.zeros((3, 2)), jnp.zeros(1))
    codes = [Result.MAX_ITERATIONS] * 3 + [Result.SUCCESS, Result.SUCCESS, Result.NONFINITE,
                                           Result.INVERTED_ELEMENT]
    soft, plain, targets = [], [], []
    for code in codes:
        t_try, _ = ctrl.target(cs, 0.0)
        soft.append(int(cs.stages.soft))
        plain.append(bool(cs.plain))
        targets.append(float(t_try))
        cs = ctrl.adapt(cs, 0.0, t_try, _outcome(code), 1)
    assert soft == [-1, -1, -1, 2, 1, 0, -1]
    assert plain == [False] * 6 + [True]
    assert targets == [0.25, 0.125] + [0.0625] * 5
    assert int(cs.code) == Result.MAX_ITERATIONS


@pytest.mark.parametrize("has_line_search", [True, False])
def test_the_stabilised_attempts_come_last_and_searched_and_their_failure_stops_the_run(has_line_search):
    """With a sheet modulus (stabilize > 0): after the floor attempt and (with a line search) the
    unsearched one, an attempt with the damper eta = stabilize E, then one with STABILIZE_RISE eta, both
    with the line search; when the second fails too, the run stops with its code."""
    ctrl = Controller.build((Phase("load", n_steps=4),), StepControl(max_cuts=2, stabilize=1e-3), False,
                            has_line_search, jnp.array(0, jnp.int32), modulus=2e5)
    assert ctrl.stabilized and float(ctrl.eta) == pytest.approx(200.0)
    cs = ctrl.init(jnp.zeros((3, 2)), jnp.zeros(1))
    targets, plain, damped = [], [], []
    codes = [Result.MAX_ITERATIONS] * (5 if has_line_search else 4) + [Result.INVERTED_ELEMENT]
    for code in codes:
        t_try, _ = ctrl.target(cs, 0.0)
        targets.append(float(t_try))
        plain.append(bool(cs.plain))
        damped.append(int(cs.damped))
        cs = ctrl.adapt(cs, 0.0, t_try, _outcome(code), 1)
    n = len(codes)
    assert targets == [0.25, 0.125] + [0.0625] * (n - 2)
    assert plain == [False] * 3 + ([True] if has_line_search else []) + [False, False]
    assert damped == [0] * (n - 2) + [1, 2]
    assert int(cs.code) == Result.INVERTED_ELEMENT and int(cs.cuts) == n


def test_a_converged_stabilised_attempt_is_the_step_and_the_next_step_is_undamped():
    """The damped attempt converges: it is an accepted step (cuts reset) and the next attempt has no
    damper; with stabilize = 0 (or no modulus) the run stops where the damped attempt would come."""
    ctrl = Controller.build((Phase("load", n_steps=4),), StepControl(max_cuts=2), False, True,
                            jnp.array(0, jnp.int32), modulus=2e5)
    cs = ctrl.init(jnp.zeros((3, 2)), jnp.zeros(1))
    for _ in range(4):   # 0.25, 0.125, 0.0625, 0.0625 unsearched
        t_try, _ = ctrl.target(cs, 0.0)
        cs = ctrl.adapt(cs, 0.0, t_try, _outcome(Result.MAX_ITERATIONS), 1)
    assert int(cs.damped) == 1 and int(cs.code) == Result.CONTINUE
    cs = ctrl.adapt(cs, 0.0, 0.0625, _outcome(Result.SUCCESS), 1)
    assert int(cs.damped) == 0 and int(cs.cuts) == 0 and int(cs.code) == Result.CONTINUE
    off = Controller.build((Phase("load", n_steps=4),), StepControl(max_cuts=2, stabilize=0.0), False, True,
                           jnp.array(0, jnp.int32), modulus=2e5)
    assert not off.stabilized
    cs, targets, _ = _failing_step(off, off.init(jnp.zeros((3, 2)), jnp.zeros(1)))
    assert targets == [0.25, 0.125, 0.0625, 0.0625] and int(cs.code) == Result.MAX_ITERATIONS


def test_crawl_count_counts_accepted_steps_at_the_floor_after_failed_attempts():
    control, nominal = StepControl(max_cuts=2), 0.25    # floor 0.0625
    count = lambda ok, cuts, n, dt: int(crawl_count(control, ok, jnp.array(cuts), jnp.array(n), dt, nominal))  # noqa: E731
    assert count(T, 2, 4, 0.0625) == 5      # at the floor after two failures: one more
    assert count(T, 0, 4, 0.0625) == 0      # at the floor at once: the crawl is over
    assert count(T, 2, 4, 0.125) == 0       # above the floor
    assert count(F, 2, 4, 0.0625) == 4      # a failed attempt leaves the count


def _crawling_step(ctrl, cs, t):
    """One step whose attempts fail until the stabilised one, which converges, each in many iterations (a
    crawl's steps are never easy): the new state and the step's end (pseudo-time)."""
    for _ in range(20):
        t_try, _ = ctrl.target(cs, t)
        code = Result.SUCCESS if int(cs.damped) > 0 else Result.MAX_ITERATIONS
        cs = ctrl.adapt(cs, t, t_try, _outcome(code, iterations=60), 1)
        if code == Result.SUCCESS:
            return cs, float(t_try)
    raise AssertionError("no stabilised attempt")


def test_steps_that_crawl_at_the_floor_stop_the_run_as_stalled():
    """Each step fails at every increment and converges only with the damper at the smallest one: the
    increment never grows back, and ``stall_steps`` such steps in a row stop the run (STALLED); one step
    accepted at its first attempt starts the count again."""
    ctrl = Controller.build((Phase("load", n_steps=4),), StepControl(max_cuts=2, stall_steps=3), False, True,
                            jnp.array(0, jnp.int32), modulus=2e5)
    cs, t = ctrl.init(jnp.zeros((3, 2)), jnp.zeros(1)), 0.0
    for n in (1, 2):
        cs, t = _crawling_step(ctrl, cs, t)
        assert int(cs.n_crawl) == n and int(cs.code) == Result.CONTINUE and float(cs.dt) == 0.0625
    t_try, _ = ctrl.target(cs, t)
    cs = ctrl.adapt(cs, t, t_try, _outcome(Result.SUCCESS), 1)
    assert int(cs.n_crawl) == 0 and int(cs.code) == Result.CONTINUE
    t = float(t_try)
    for n in (1, 2):
        cs, t = _crawling_step(ctrl, cs, t)
        assert int(cs.code) == Result.CONTINUE
    cs, t = _crawling_step(ctrl, cs, t)
    assert int(cs.n_crawl) == 3 and int(cs.code) == Result.STALLED and t < 1.0


def test_a_log_file_gets_a_progress_line_per_tenth_and_one_after_a_minute_without_one(monkeypatch):
    """In a log file the bar is one line per tenth of the load path; a run whose steps have shrunk (a
    tenth that takes hours) still prints its step count once a minute."""
    import io

    from jaxfric.loadpath import progress

    clock = [100.0]
    monkeypatch.setattr(progress.time, "perf_counter", lambda: clock[0])
    out = io.StringIO()
    with progress.ProgressMonitor(total_time=3.0, stream=out) as monitor:
        for step, (seconds, t) in enumerate([(1.0, 0.1), (2.0, 0.31), (30.0, 0.32), (59.0, 0.33), (62.0, 0.34),
                                             (63.0, 0.35), (64.0, 0.65)]):
            clock[0] = 100.0 + seconds
            monitor.update(step, t, iterations=5, cuts=0)
    lines = out.getvalue().splitlines()
    assert [line.split(" step ")[1].split()[0] for line in lines] == ["1", "4", "6"]
    assert all(line.endswith("s") and "t=" in line for line in lines)


def test_a_note_between_chunks_is_a_line_of_its_own_under_the_bar():
    """An event of the run (exact contact's band widened) gets a line of its own: after the bar's line in a
    log file, on a new line below the bar on a terminal; none when the bar is off."""
    import io

    from jaxfric.loadpath import progress

    class Terminal(io.StringIO):
        def isatty(self):
            return True

    for stream, expected in ((io.StringIO(), "\nband widened\n"), (Terminal(), "s\nband widened\n\r")):
        with progress.ProgressMonitor(total_time=3.0, stream=stream, min_interval=0.0) as monitor:
            monitor.update(1, 0.5, iterations=5, cuts=0)
            monitor.note("band widened")
            monitor.update(2, 1.0, iterations=5, cuts=0)
        assert expected in stream.getvalue() and stream.getvalue().count("band widened") == 1
    quiet = io.StringIO()
    with progress.ProgressMonitor(total_time=3.0, stream=quiet, show=False) as monitor:
        monitor.note("band widened")
    assert quiet.getvalue() == ""
