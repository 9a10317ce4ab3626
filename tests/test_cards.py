"""Bead cards (jaxfric.cards): the exported files read back by readers of the formats written here from
the formats' descriptions (fixed-width fields), and a small card computed from the blankholder."""

import csv
import glob
import io
import json
import os

import numpy as np
import pytest

from jaxfric.cards import BeadCard, bead_card, csv_table, lsdyna_deck, radioss_interface
from jaxfric.cards.formats import CSV_COLUMNS, line_friction, load_card

CARDS = os.path.join(os.path.dirname(__file__), os.pardir, "experiments", "results", "bead_cards")


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


def _read_radioss(text: str) -> dict:
    """/INTER/TYPE8's id, its integer line (fields of 10) and Fn, Ft, DEPTH, Tstart, Tstop (fields of 20)."""
    lines = [ln for ln in text.splitlines() if not ln.startswith("#")]
    k = next(i for i, ln in enumerate(lines) if ln.startswith("/INTER/TYPE8/"))
    fn, ft, depth, t_start, t_stop = (float(v) for v in _fields(lines[k + 3], 20))
    return {"id": int(lines[k].split("/")[3]), "ints": [int(v) for v in _fields(lines[k + 2], 10)],
            "Fn": fn, "Ft": ft, "DEPTH": depth, "Tstart": t_start, "Tstop": t_stop}


def _read_csv(text: str) -> tuple[list[str], np.ndarray]:
    rows = list(csv.reader(line for line in io.StringIO(text) if not line.startswith("#")))
    return rows[0], np.array(rows[1:], dtype=float)


def _check_files_read_back(card: BeadCard, deck_text: str, radioss_text: str, csv_text: str, rtol: float) -> None:
    """Every number a card's files carry, read back with the readers above, against the card."""
    deck = _read_lsdyna(deck_text)
    card2, card4 = deck["drawbead"][1], deck["drawbead"][3]
    fs = float(card2[0])
    assert float(card2[1]) == fs and fs == pytest.approx(line_friction(card), rel=1e-5)
    lcid_rf, lcid_nf = int(card4[0]), int(card4[1])
    assert float(card4[2]) == pytest.approx(card.depth, rel=1e-4)
    np.testing.assert_allclose(deck["curves"][lcid_rf], np.c_[card.penetration, card.bending_force], rtol=rtol)
    np.testing.assert_allclose(deck["curves"][lcid_nf], np.c_[card.penetration, card.normal_force], rtol=rtol)
    # What LS-DYNA adds up at full depth, the bending curve and FS times the normal force, is the card's total.
    total = deck["curves"][lcid_rf][-1, 1] + fs * deck["curves"][lcid_nf][-1, 1]
    assert total == pytest.approx(card.restraining_force[-1], rel=1e-5)
    rad = _read_radioss(radioss_text)
    assert (rad["Fn"], rad["Ft"], rad["DEPTH"]) == pytest.approx(
        (card.normal_force[-1], card.restraining_force[-1], card.depth), rel=rtol)
    header, data = _read_csv(csv_text)
    assert header == [h for h, _ in CSV_COLUMNS]
    for j, (_, attr) in enumerate(CSV_COLUMNS):
        np.testing.assert_allclose(data[:, j], np.asarray(getattr(card, attr)), rtol=rtol, atol=0)


def test_lsdyna_deck_reads_back_the_bending_and_normal_force_curves():
    card = _card()
    text = lsdyna_deck(card)
    deck = _read_lsdyna(text)
    card1, card2, card3, card4 = deck["drawbead"]
    assert len(card1) == len(card2) == len(card3) == 8 and len(card4) == 7
    # FS, FD: the bead line's effective friction, with which the contact's FS times the normal force is the
    # card's friction component at full depth (43.857 / 151.73), not the sheet's mu = 0.12.
    assert float(card2[0]) == float(card2[1]) == pytest.approx(43.857123456789 / 151.73, rel=1e-6)
    lcid_rf, lcid_nf, dbdth = int(card4[0]), int(card4[1]), float(card4[2])
    assert dbdth == card.depth
    np.testing.assert_allclose(deck["curves"][lcid_rf], np.c_[card.penetration, card.bending_force], rtol=1e-11)
    np.testing.assert_allclose(deck["curves"][lcid_nf], np.c_[card.penetration, card.normal_force], rtol=1e-11)
    lines = text.splitlines()
    curve_headers = [lines[i + 3] for i, ln in enumerate(lines) if ln.startswith("*DEFINE_CURVE")]
    assert len(curve_headers) == 2
    assert all(len(_fields(h, 10)) == 8 for h in curve_headers)   # LCID SIDR SFA SFO OFFA OFFO DATTYP LCINT
    assert all(len(line) <= 80 for line in lines if not line.startswith("$"))
    _check_files_read_back(card, text, radioss_interface(card), csv_table(card), rtol=1e-11)


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


@pytest.mark.xla_optimized   # mostly run time (tests/conftest.py)
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
    texts = {}
    for name in ("lsdyna", "radioss", "csv"):
        with open(paths[name]) as fh:
            texts[name] = fh.read()
    _check_files_read_back(card, texts["lsdyna"], texts["radioss"], texts["csv"], rtol=1e-11)
    back = load_card(paths["json"])
    np.testing.assert_array_equal(back.restraining_force, card.restraining_force)
    np.testing.assert_array_equal(back.normal_force, card.normal_force)


def _committed_cards() -> list[str]:
    return sorted(os.path.dirname(p) for p in glob.glob(os.path.join(CARDS, "*", "bead_card.json")))


def test_committed_cards_cover_the_nine_shapes_and_their_files_read_back():
    """The cards of ``experiments/bead_cards.py`` in the repository: shapes 1 to 9 at the paper's material, each
    with its LS-DYNA, OpenRadioss and CSV files, which read back to the card's JSON (the numbers as written:
    12 significant digits on the curves and in the CSV, 6 for FS)."""
    dirs = _committed_cards()
    names = {os.path.basename(d) for d in dirs}
    assert {f"shape{k}" for k in range(1, 10)} <= names
    for d in dirs:
        card = load_card(os.path.join(d, "bead_card.json"))
        texts = []
        for ext in ("k", "rad", "csv"):
            with open(os.path.join(d, f"bead_card.{ext}")) as fh:
                texts.append(fh.read())
        assert os.path.exists(os.path.join(d, "bead_card.png"))
        _check_files_read_back(card, *texts, rtol=1e-11)


def test_committed_cards_agree_with_their_full_blankholder_runs_within_the_runs_error_estimate():
    """Each committed card's restraining and normal forces at full depth (pulled 35 to 58 mm, the last 10 mm
    its window) against the full-depth bead drawn the spec's whole 55 mm with the spec's window [35, 55] mm
    (``experiments/bead_cards.py``'s consistency run): within that run's error estimates (the normal
    force's: the same components, its own scatter over the window)."""
    checked = 0
    for d in _committed_cards():
        with open(os.path.join(d, "bead_card.json")) as fh:
            s = json.load(fh)
        check, label = s["consistency"], os.path.basename(d)
        assert check["converged"], (label, check)
        difference = s["restraining_force"][-1] - check["steady_drawing_force"]
        assert abs(difference) <= check["error_estimate"], (label, difference, check["error_estimate"])
        difference = s["normal_force"][-1] - check["steady_normal_force"]
        assert abs(difference) <= check["normal_error_estimate"], (label, difference, check["normal_error_estimate"])
        checked += 1
    assert checked >= 9


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
        difference, rel = _status_preserving_difference(steady, par.p0, i, name)
        got = [card.derivatives[name][k][-1] for k in ("restraining_force", "normal_force")]
        np.testing.assert_allclose(got, difference, rtol=1e-5, err_msg=f"{name}, h = {rel:g}")


def _status_preserving_difference(values, p0, i: int, name: str, rels=(1e-6, 1e-7, 1e-8)):
    """The central difference of ``values(p) -> (outputs, contact statuses)`` in parameter ``i`` with the
    largest h of ``rels`` times its value within which no contact status changes between the two replays;
    (difference, h)."""
    for rel in rels:
        step = rel * p0[i] * np.eye(len(p0))[i]
        (up, status_up), (down, status_down) = values(p0 + step), values(p0 - step)
        if np.array_equal(status_up, status_down):
            return (up - down) / (2 * step[i]), rel
    pytest.fail(f"a contact status changes within +-1e-8 of {name}")


@pytest.mark.slow
def test_card_derivatives_of_the_bending_part_thinning_and_plastic_strain_match_central_differences():
    """shape1 on 1 mm elements at full depth, pulled the card's 35 mm (the sheet that lay upstream then lies
    over the downstream land): d(thinning, mean and largest eqps after the bead)/d(mu, t) from the final
    state and d(bending part)/d(t) from the frictionless run, against central differences of the replayed
    steps (h = 1e-7 of the value, or 1e-8 where a contact status changes between the two replays), to
    1e-5 of the row's largest entry. The final state's differences need the smaller h: for mu they move
    by 5.2e-5, 1.0e-5 and 5e-8 from the forward-mode derivative of the thinning (0.0898) at h = 1e-5,
    1e-6 and 1e-7 of the value, with no status change, a truncation error that h = 1e-6 leaves at 1.1e-4
    of the value."""
    import jax.numpy as jnp

    from jaxfric.cards.bead import _after_bead_columns, _after_bead_values, card_overrides
    from jaxfric.identification.params import adaptive_run, parameterize, path_function
    from jaxfric.io.instants import steady_rows

    names = ("mu", "t")
    base = {"element_length": 1.0}
    card = bead_card("shape1", penetrations=(1.0,), overrides=base, derivatives=names)
    assert np.isfinite(card.thinning[-1]) and card.thinning[-1] > 0.05
    assert card.derivatives["mu"]["bending_force"][-1] == 0.0

    def differences(mu: float, outputs, names):
        par = parameterize("blankholder", names, variant="shape1", algorithm="lcp_ssn",
                           overrides=card_overrides("shape1", 6.0, {**base, "mu": mu}))
        plan = adaptive_run(par, par.p0).history
        f = path_function(par, plan=plan, final=True)
        scene = par.scene
        mesh = scene.model.mesh
        u = np.asarray(plan["drawing_displacement"])
        rows = steady_rows(plan["phase_name"], u, scene.steady_window)
        cols = None

        def values(p):
            nonlocal cols
            h, _, final, nodes = f(jnp.asarray(p))
            if cols is None:
                cols = _after_bead_columns(scene, final)
            force = np.trapezoid(np.asarray(h.observed["drawing_force"])[rows], u[rows]) / (u[rows][-1] - u[rows][0])
            after = _after_bead_values(cols, nodes, final.u, final.material.eqps, p[-1], mesh.nx, mesh.ny)
            status = np.stack([np.asarray(h.observed[k]) for k in ("n_active", "n_slip")])
            return np.array([force, *(float(v) for v in after)])[outputs], status

        values(par.p0)
        return {name: _status_preserving_difference(values, par.p0, i, name, rels=(1e-7, 1e-8))[0]
                for i, name in enumerate(names)}

    with_friction = differences(0.15, [1, 2, 3], names)
    for name in names:
        got = [card.derivatives[name][k][-1] for k in ("thinning", "eqps_after", "eqps_after_max")]
        np.testing.assert_allclose(got, with_friction[name], rtol=0, atol=1e-5 * np.max(np.abs(got)), err_msg=name)
    frictionless = differences(0.0, [0], ("t",))
    assert card.derivatives["t"]["bending_force"][-1] == pytest.approx(frictionless["t"][0], rel=1e-5)
