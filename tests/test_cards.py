"""Bead cards (jaxfric.cards): the exported files read back by readers of the formats written here from
the formats' descriptions (fixed-width fields), and a small card computed from the blankholder."""

import csv
import io

import numpy as np
import pytest

from jaxfric.cards import BeadCard, bead_card, csv_table, lsdyna_deck, radioss_interface
from jaxfric.cards.formats import CSV_COLUMNS


def _card() -> BeadCard:
    """A card with values of every size a deck meets (made here, not computed)."""
    d = np.array([0.0, 1.5, 3.0, 4.5, 6.0])
    return BeadCard(variant="shape1", overrides={"mu": 0.12}, depth=6.0, thickness=1.0, mu=0.12, penetration=d,
                    restraining_force=np.array([0.0, 12.25, 40.5, 95.125, 142.357123456789]),
                    bending_force=np.array([0.0, 8.0, 27.75, 64.0, 98.5]),
                    normal_force=np.array([0.0, 14.0, 41.0, 99.9, 151.73]),
                    normal_force_bending=np.array([0.0, 13.0, 39.0, 95.0, 146.0]),
                    scatter=np.array([0.0, 0.5, 0.7, 0.8, 0.9]), thinning=np.array([0.0, 0.001, 0.004, 0.01, 0.02]),
                    eqps_after=np.array([0.0, 0.01, 0.03, 0.06, 0.1]),
                    eqps_after_max=np.array([0.0, 0.02, 0.05, 0.09, 0.15]))


def _fields(line: str, width: int) -> list[str]:
    return [line[i:i + width].strip() for i in range(0, len(line.rstrip()), width)]


def _read_lsdyna(text: str) -> dict:
    """*CONTACT_DRAWBEAD's four cards (10-character fields) and the *DEFINE_CURVE tables (a header card of
    10-character fields, then abscissa/ordinate in two 20-character fields), comments ($) skipped."""
    out: dict = {"curves": {}}
    keyword, cards = None, []

    def close():
        if keyword == "*CONTACT_DRAWBEAD":
            out["drawbead"] = [_fields(c, 10) for c in cards]
        elif keyword == "*DEFINE_CURVE":
            lcid = int(_fields(cards[0], 10)[0])
            out["curves"][lcid] = np.array([[float(c[:20]), float(c[20:40])] for c in cards[1:]])

    for line in text.splitlines():
        if line.startswith("$"):
            continue
        if line.startswith("*"):
            close()
            keyword, cards = line.strip(), []
        else:
            cards.append(line)
    close()
    return out


def test_lsdyna_deck_reads_back_the_bending_and_normal_force_curves():
    card = _card()
    deck = _read_lsdyna(lsdyna_deck(card))
    card1, card2, card3, card4 = deck["drawbead"]
    assert len(card1) == len(card2) == len(card3) == 8 and len(card4) == 7
    assert float(card2[0]) == float(card2[1]) == card.mu        # FS, FD: the contact adds mu times the normal force
    lcid_rf, lcid_nf, dbdth = int(card4[0]), int(card4[1]), float(card4[2])
    assert dbdth == card.depth
    np.testing.assert_allclose(deck["curves"][lcid_rf], np.c_[card.penetration, card.bending_force], rtol=1e-11)
    np.testing.assert_allclose(deck["curves"][lcid_nf], np.c_[card.penetration, card.normal_force], rtol=1e-11)
    assert all(len(line) <= 80 for line in lsdyna_deck(card).splitlines() if not line.startswith("$"))


def test_lsdyna_total_option_puts_the_whole_restraining_force_in_the_curve_and_no_friction():
    card = _card()
    deck = _read_lsdyna(lsdyna_deck(card, total=True, lcids=(11, 12)))
    assert float(deck["drawbead"][1][0]) == 0.0 and float(deck["drawbead"][1][1]) == 0.0
    np.testing.assert_allclose(deck["curves"][11][:, 1], card.restraining_force, rtol=1e-11)
    np.testing.assert_allclose(card.friction_force, card.restraining_force - card.bending_force)


def test_radioss_type8_carries_the_full_depth_forces_and_the_depth():
    card = _card()
    lines = [ln for ln in radioss_interface(card, inter_id=7).splitlines() if not ln.startswith("#")]
    k = next(i for i, ln in enumerate(lines) if ln.startswith("/INTER/TYPE8/"))
    assert lines[k].split("/")[3] == "7"
    ids = [int(v) for v in _fields(lines[k + 2], 10)]
    fn, ft, depth, t_start, t_stop = (float(v) for v in _fields(lines[k + 3], 20))
    assert len(ids) == 3
    assert (fn, ft, depth) == pytest.approx((card.normal_force[-1], card.restraining_force[-1], card.depth), rel=1e-11)
    assert t_start == 0.0 and t_stop > 1e29


def test_csv_table_has_units_in_its_header_and_every_column():
    card = _card()
    text = csv_table(card)
    rows = list(csv.reader(line for line in io.StringIO(text) if not line.startswith("#")))
    header, data = rows[0], np.array(rows[1:], dtype=float)
    assert header == [h for h, _ in CSV_COLUMNS] and all("(" in h and h.endswith(")") for h in header)
    for j, (_, attr) in enumerate(CSV_COLUMNS):
        np.testing.assert_allclose(data[:, j], np.asarray(getattr(card, attr)), rtol=1e-11, atol=0)


def test_penetrations_and_card_owned_fields_are_checked():
    with pytest.raises(ValueError, match="penetrations"):
        bead_card("shape1", penetrations=(0.5, 1.2))
    with pytest.raises(ValueError, match="closure"):
        bead_card("shape1", overrides={"closure": 3.0})


SMALL = {"element_length": 1.0, "U_pull": 6.0, "steady_window": (4.0, 6.0)}  # shape1 on 1 mm elements


def test_small_card_rises_with_penetration_and_splits_bending_from_friction(tmp_path):
    """shape1 on 1 mm elements, pulled 6 mm (window [4, 6] mm), at half and full depth, with its mu = 0.15 and
    without friction: both forces rise with the penetration, both parts of the restraining force are
    positive (measured at full depth: 177.8 N/mm, of which 112.0 bending), and the written deck carries
    the computed curve. Too short a pull for any sheet to pass the whole bead: thinning is NaN, and said."""
    card = bead_card("shape1", penetrations=(0.5, 1.0), overrides=SMALL)
    assert card.penetration.tolist() == [0.0, 3.0, 6.0]
    assert np.all(np.diff(card.restraining_force) > 0) and np.all(np.diff(card.normal_force) > 0)
    assert np.all(card.friction_force[1:] > 0) and np.all(card.bending_force[1:] > 0)
    assert np.all(np.isnan(card.thinning[1:]))
    from jaxfric.cards import write_card
    paths = write_card(card, str(tmp_path))
    with open(paths["lsdyna"]) as fh:
        deck = _read_lsdyna(fh.read())
    np.testing.assert_allclose(deck["curves"][1][:, 1], card.bending_force, rtol=1e-11)


@pytest.mark.slow
def test_card_derivatives_match_central_differences_along_the_same_steps():
    """d(restraining, normal force)/d(mu, t) of the small card at full depth against central differences of
    the replayed step sequence, with h = 1e-6 of the value, where no pair changes its contact status
    between the two replays, else 1e-7 or 1e-8 (checked: at 1e-5 of mu one row of the 191 does, and the
    difference then misses the derivative by 0.8 % and 3.5 %; for t one does at 1e-6): to 1e-5 (measured
    3e-8 for mu)."""
    import jax.numpy as jnp

    from jaxfric.cards.bead import card_overrides
    from jaxfric.identification.params import adaptive_run, parameterize, path_function
    from jaxfric.io.instants import steady_rows

    names = ("mu", "t")
    card = bead_card("shape1", penetrations=(1.0,), overrides=SMALL, derivatives=names)
    par = parameterize("blankholder", names, variant="shape1", algorithm="lcp_ssn",
                       overrides=card_overrides("shape1", 6.0, SMALL))
    plan = adaptive_run(par, par.p0).history
    f = path_function(par, plan=plan)
    u = np.asarray(plan["drawing_displacement"])
    rows = steady_rows(plan["phase_name"], u, SMALL["steady_window"])

    def steady(p):
        h, _ = f(jnp.asarray(p))
        forces = np.array([np.trapezoid(np.asarray(h.observed[k])[rows], u[rows]) / (u[rows][-1] - u[rows][0])
                           for k in ("drawing_force", "clamping_force")])
        return forces, np.stack([np.asarray(h.observed[k]) for k in ("n_active", "n_slip")])

    assert steady(par.p0)[0][0] == pytest.approx(card.restraining_force[-1], rel=1e-9)
    for i, name in enumerate(names):
        for rel in (1e-6, 1e-7, 1e-8):  # the largest h within which no status changes
            step = rel * par.p0[i] * np.eye(len(names))[i]
            (up, status_up), (down, status_down) = steady(par.p0 + step), steady(par.p0 - step)
            if np.array_equal(status_up, status_down):
                break
        else:
            pytest.fail(f"a contact status changes within +-1e-8 of {name}")
        got = [card.derivatives[name][k][-1] for k in ("restraining_force", "normal_force")]
        np.testing.assert_allclose(got, (up - down) / (2 * step[i]), rtol=1e-5, err_msg=f"{name}, h = {rel:g}")
