"""A bead card in the input formats of stamping codes (``../shared/spec/drawbead_cards.md``).

- LS-DYNA (:func:`lsdyna_deck`): ``*CONTACT_DRAWBEAD`` with its card 4 ``LCIDRF LCIDNF DBDTH DFSCL NUMINT
  DBPID ELOFF`` and two ``*DEFINE_CURVE`` (header ``LCID SIDR SFA SFO OFFA OFFO DATTYP LCINT``): the
  restraining force's bending component (``LCIDRF``) and the normal force (``LCIDNF``), per unit bead
  length against the bead displacement 0 .. DBDTH. The contact adds its friction as FS times the normal
  force, so FS = FD = the bead line's effective coefficient (:func:`line_friction`: the card's friction
  component over its normal force at full depth), with which the deck's restraining force at full depth
  is the card's. It is not the sheet's mu: the friction acts on the sheet's wraps around the bead's
  radii, whose normal forces add up to more than the bead's opening force (0.285 to 0.323 against mu = 0.15
  on the nine shapes; docs/results.md, bead cards). With ``total`` the first curve is the whole
  restraining force and FS = FD = 0 (the friction then is in the curve, exact at every penetration).
  Fields of 10 characters on the cards, abscissa and ordinate in two fields of 20 on the curves' lines,
  ``$`` comment lines giving the units and what to fill in (the bead line's node set SSID and the blank's
  part MSID are the deck's).
- OpenRadioss (:func:`radioss_interface`): ``/INTER/TYPE8`` with the full-depth values Fn (normal force)
  and Ft (restraining force) per unit length and DEPTH, the block format's integers in fields of 10
  characters and reals in fields of 20. The solver ramps the normal force linearly with penetration up
  to Fn and caps the restraining force at Ft, so only the full-depth values enter; the comments say which
  depth and friction they assume.
- CSV (:func:`csv_table`): every column of the card with its unit in the header, after ``#`` lines of
  metadata (bead, sheet, friction, units); JSON (:func:`card_summary`): every field, derivatives included.

Units: the card's, mm and N per mm of bead length (N/mm); a deck in other units scales them (LS-DYNA's
SFA/SFO, DFSCL).
"""

from __future__ import annotations

import io
import json

import numpy as np

from ..io.output import json_ready
from .bead import BeadCard

__all__ = ["lsdyna_deck", "radioss_interface", "csv_table", "CSV_COLUMNS", "card_summary", "write_card", "load_card",
           "line_friction"]

# (header, attribute or function of the card) of the CSV, in order.
CSV_COLUMNS = (
    ("penetration (mm)", "penetration"),
    ("restraining force (N/mm)", "restraining_force"),
    ("bending component (N/mm)", "bending_force"),
    ("friction component (N/mm)", "friction_force"),
    ("normal force (N/mm)", "normal_force"),
    ("normal force without friction (N/mm)", "normal_force_bending"),
    ("restraining force scatter (N/mm)", "scatter"),
    ("thinning after the bead (-)", "thinning"),
    ("mean eqps after the bead (-)", "eqps_after"),
    ("largest eqps after the bead (-)", "eqps_after_max"),
)


def _f10(v, digits: int = 4) -> str:
    """A number in a 10-character field (LS-DYNA's and OpenRadioss's integer fields, LS-DYNA's reals, to
    ``digits`` significant digits)."""
    if isinstance(v, (int, np.integer)):
        text = str(int(v))
    else:
        text = f"{float(v):.{digits}g}" if abs(float(v)) < 1e5 else f"{float(v):.3e}"
    if len(text) > 10:
        raise ValueError(f"value {v!r} does not fit a 10-character field")
    return text.rjust(10)


def _f20(v: float) -> str:
    return f"{float(v):.12g}".rjust(20)


def _meta(card: BeadCard, comment: str) -> list[str]:
    return [f"{comment} jaxfric bead card: blankholder {card.variant}, bead depth {card.depth:g} mm, sheet "
            f"t = {card.thickness:g} mm, mu = {card.mu:g}",
            f"{comment} units: mm, N/mm (force per unit bead length); overrides {card.overrides or {}}"]


def line_friction(card: BeadCard) -> float:
    """The bead line's effective friction coefficient: the card's friction component over its normal force at
    full depth (the sheet's mu where the normal force is zero), so that bending component + coefficient x
    normal force is the card's restraining force at full depth (LS-DYNA's FS, FD; module docstring)."""
    normal = float(card.normal_force[-1])
    return float(card.friction_force[-1]) / normal if normal > 0.0 else float(card.mu)


def _law_note(card: BeadCard, total: bool) -> list[str]:
    """A comment for a card made with a friction law of pressure or speed: FS = FD holds the law's effect at the
    card's pressures and speed, and no decay of its own."""
    law = (card.overrides or {}).get("friction_law", "coulomb")
    if law == "coulomb" or total:
        return []
    return [f"$ friction_law = {law}: FS = FD is the effective coefficient at the card's pressures and drawing speed,",
            "$ with no pressure or speed dependence of its own (DC = 0)"]


def lsdyna_deck(card: BeadCard, *, ssid: int = 1, msid: int = 2, sstyp: int = 4, mstyp: int = 3,
                lcids: tuple[int, int] = (1, 2), total: bool = False) -> str:
    """The LS-DYNA keyword text: ``*CONTACT_DRAWBEAD`` (cards 1 to 4) and the two ``*DEFINE_CURVE``
    (module docstring). ``ssid``/``sstyp``: the bead line's set and its type (4: node set), ``msid``/
    ``mstyp``: the blank (3: part)."""
    lcid_rf, lcid_nf = lcids
    fs = 0.0 if total else line_friction(card)
    rf = card.restraining_force if total else card.bending_force
    what = "restraining force (total)" if total else "bending component of the restraining force"
    if total:
        friction = ["$ FS = FD = 0: the friction component is in the LCIDRF curve"]
    else:
        ff, nf, rf_h = float(card.friction_force[-1]), float(card.normal_force[-1]), float(card.restraining_force[-1])
        friction = [f"$ FS = FD = {fs:.6g}: the bead line's effective friction, friction component / normal",
                    f"$ force at full depth ({ff:.6g} / {nf:.6g} N/mm), not the sheet's mu = {card.mu:g}; with it",
                    f"$ the restraining force at full depth is the card's {rf_h:.6g} N/mm, "
                    f"of which {float(card.bending_force[-1]):.6g} bending"]
    out = ["*KEYWORD", *_meta(card, "$"),
           f"$ LCIDRF: {what}; LCIDNF: normal force; abscissa: bead displacement 0 .. DBDTH (mm)",
           "$ set SSID (the bead line) and MSID (the blank) to the deck's own ids",
           *friction,
           *_law_note(card, total),
           "*CONTACT_DRAWBEAD",
           "$     SSID      MSID     SSTYP     MSTYP    SBOXID    MBOXID       SPR       MPR",
           "".join(_f10(v) for v in (ssid, msid, sstyp, mstyp, 0, 0, 0, 0)),
           "$       FS        FD        DC        VC       VDC    PENCHK        BT        DT",
           "".join(_f10(v, digits=6) for v in (fs, fs, 0.0, 0.0, 0.0, 0, 0.0, 1e20)),
           "$      SFS       SFM       SST       MST      SFST      SFMT       FSF       VSF",
           "".join(_f10(v) for v in (1.0, 1.0, 0.0, 0.0, 1.0, 1.0, 1.0, 1.0)),
           "$   LCIDRF    LCIDNF     DBDTH     DFSCL    NUMINT     DBPID     ELOFF",
           "".join(_f10(v) for v in (lcid_rf, lcid_nf, card.depth, 1.0, 0, 0, 0))]
    for lcid, title, values in ((lcid_rf, what, rf), (lcid_nf, "normal force", card.normal_force)):
        out += ["*DEFINE_CURVE", f"$ {title} (N/mm) against bead displacement (mm)",
                "$     LCID      SIDR       SFA       SFO      OFFA      OFFO    DATTYP     LCINT",
                "".join(_f10(v) for v in (lcid, 0, 1.0, 1.0, 0.0, 0.0, 0, 0)),
                "$                 A1                  O1"]
        out += [_f20(a) + _f20(o) for a, o in zip(card.penetration, values, strict=True)]
    out.append("*END")
    return "\n".join(out) + "\n"


def radioss_interface(card: BeadCard, *, inter_id: int = 1, unit_id: int = 0, grnd_ids: int = 1,
                      surf_idm: int = 1, iform: int = 0, total: bool = True) -> str:
    """The OpenRadioss ``/INTER/TYPE8`` block (module docstring): Fn, Ft and DEPTH at full depth;
    ``total``: Ft is the whole restraining force (the interface adds no friction of its own), otherwise
    its bending component."""
    ft = card.restraining_force[-1] if total else card.bending_force[-1]
    lines = [*_meta(card, "#"),
             f"# Fn, Ft: normal and {'restraining' if total else 'bending restraining'} force per unit length at "
             f"full depth {card.penetration[-1]:g} mm",
             f"/INTER/TYPE8/{inter_id}/{unit_id}" if unit_id else f"/INTER/TYPE8/{inter_id}",
             f"jaxfric bead card {card.variant}",
             "#grnd_IDs  surf_IDm     Iform",
             _f10(grnd_ids) + _f10(surf_idm) + _f10(iform),
             "#                 Fn                  Ft               DEPTH              Tstart               Tstop",
             _f20(card.normal_force[-1]) + _f20(ft) + _f20(card.depth) + _f20(0.0) + _f20(1e30)]
    return "\n".join(lines) + "\n"


def csv_table(card: BeadCard) -> str:
    """The card as CSV: ``#`` metadata lines, a header with units, one row per penetration."""
    buf = io.StringIO()
    for line in _meta(card, "#"):
        buf.write(line + "\n")
    buf.write(",".join(h for h, _ in CSV_COLUMNS) + "\n")
    columns = [np.asarray(getattr(card, attr)) for _, attr in CSV_COLUMNS]
    for row in zip(*columns, strict=True):
        buf.write(",".join(f"{float(v):.12g}" for v in row) + "\n")
    return buf.getvalue()


def card_summary(card: BeadCard) -> dict:
    """Every field of the card, its friction part and its line's effective friction, JSON-ready
    (``bead_card.json``; :func:`load_card` reads it back)."""
    return json_ready(dict(card.__dict__, friction_force=card.friction_force, line_friction=line_friction(card)))


def load_card(path: str) -> BeadCard:
    """The :class:`BeadCard` of a ``bead_card.json`` that :func:`write_card` wrote (its other entries, such as
    the experiments' ``consistency``, are left out)."""
    import dataclasses

    with open(path) as fh:
        s = json.load(fh)
    arrays = {f.name for f in dataclasses.fields(BeadCard)} - {"variant", "overrides", "depth", "thickness", "mu",
                                                                "derivatives", "wall_s", "notes"}
    fields = {f.name: s[f.name] for f in dataclasses.fields(BeadCard) if f.name in s}
    fields.update({k: np.asarray(s[k], dtype=float) for k in arrays})
    fields["derivatives"] = {name: {k: np.asarray(v, dtype=float) for k, v in d.items()}
                             for name, d in s.get("derivatives", {}).items()}
    fields["notes"] = tuple(s.get("notes", ()))
    # JSON has no tuples: the config's sequence fields (back stresses, a steady window) come back as lists.
    fields["overrides"] = {k: tuple(v) if isinstance(v, list) else v for k, v in (s.get("overrides") or {}).items()}
    return BeadCard(**fields)


def write_card(card: BeadCard, out_dir: str, *, total: bool = False, extra: dict | None = None) -> dict:
    """Write ``bead_card.k`` (LS-DYNA), ``bead_card.rad`` (OpenRadioss), ``bead_card.csv``,
    ``bead_card.json`` (:func:`card_summary`, with ``extra`` entries) and ``bead_card.png`` into
    ``out_dir``; returns {format: path}."""
    import os

    os.makedirs(out_dir, exist_ok=True)
    paths = {name: os.path.join(out_dir, f"bead_card.{ext}") for name, ext in
             (("lsdyna", "k"), ("radioss", "rad"), ("csv", "csv"), ("json", "json"), ("figure", "png"))}
    summary = json.dumps({**card_summary(card), **json_ready(extra or {})}, indent=1)
    for name, text in (("lsdyna", lsdyna_deck(card, total=total)), ("radioss", radioss_interface(card)),
                       ("csv", csv_table(card)), ("json", summary)):
        with open(paths[name], "w") as fh:
            fh.write(text)
    _figure(card, paths["figure"])
    return paths


def _figure(card: BeadCard, path: str) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4.5), constrained_layout=True)
    d = card.penetration
    ax.plot(d, card.restraining_force, "o-", label="restraining force")
    ax.plot(d, card.bending_force, "s--", label="bending component (mu = 0)")
    ax.plot(d, card.friction_force, "^:", label="friction component")
    ax.plot(d, card.normal_force, "d-", label="normal (opening) force")
    ax.set(xlabel="bead penetration (mm)", ylabel="force per unit bead length (N/mm)",
           title=f"bead card: blankholder {card.variant}, t = {card.thickness:g} mm, mu = {card.mu:g}",
           xlim=(0.0, card.depth))
    ax.grid(alpha=0.3)
    ax.legend()
    fig.savefig(path, dpi=110)
    plt.close(fig)
