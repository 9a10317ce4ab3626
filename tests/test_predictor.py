"""The secant predictor of the adaptive load loop (jaxfric.loadpath.simulate._Predictor): used where it
works, withheld where it keeps failing."""

import equinox as eqx

from jaxfric.loadpath.model import initial_state
from jaxfric.loadpath.simulate import _Predictor
from jaxfric.scenes import make


def test_a_failing_prediction_is_withheld_for_doubling_spans_and_used_again_once_it_converges():
    model = make("flat_die", None, "penalty", {"mesh": "4x1"}).model
    old = initial_state(model)
    new = eqx.tree_at(lambda s: s.time, old, old.time + 0.1)
    p = _Predictor.empty(old)
    assert not p.used(old, old.phase)               # nothing to extrapolate yet
    p = p.after(True, old, new)                     # an accepted step: its increment is the prediction
    assert p.used(old, old.phase) and not p.used(old, old.phase, retry=True)

    def fail_then_count(p, span):
        """A predicted attempt fails: the step (retried from the converged state, cut or not) and the
        next ``span`` steps start converged."""
        p = p.after(False, old, new, predicted=True)
        p = p.after(False, old, new)
        for _ in range(span + 1):
            assert not p.used(old, old.phase)
            p = p.after(True, old, new)
        assert p.used(old, old.phase)
        return p

    for span in (1, 2, 4, 8, 16, 32, 32):           # doubling while it keeps failing, up to MAX_HOLD
        p = fail_then_count(p, span)
    p = p.after(True, old, new, predicted=True)     # a predicted attempt converges: the span starts again
    fail_then_count(p, 1)
