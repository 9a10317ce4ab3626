"""A friction law in the input formats of stamping codes (``../shared/spec/drawbead_cards.md``).

- OpenRadioss (:func:`radioss_friction`): ``/FRICTION`` with ``Ifric`` = 1, the generalised viscous law
  mu = Fric + C1 p + C2 v + C3 p v + C4 p^2 + C5 v^2, which a :class:`~jaxfric.contact.friction.Polynomial`
  fills term by term (Fric = mu_0); or ``Ifric`` = 4, the exponential decay mu = C1 + (Fric - C1)
  exp(-C2 v), v the magnitude of the sliding speed, which a :class:`~jaxfric.contact.friction.VelocityDecay`
  fills as Fric = mu_0, C1 = mu_d, C2 = decay (OpenRadioss's contact force routines, for example
  ``engine/source/interfaces/int07/i7for3.F``, and its starter's printout of the law). Lines: the
  integers ``Ifric``, ``Ifiltr`` in fields of 10 characters, ``Xfreq`` in 20 and ``Iform`` in 10; then
  C1 .. C5 and C6, Fric, VISF in fields of 20 (blank fields take the code's defaults). The parts or groups
  it applies to, and the interfaces that use it, are the deck's.
- LS-DYNA (:func:`lsdyna_friction`): card 2 of a ``*CONTACT_...`` keyword, ``FS FD DC VC VDC PENCHK BT
  DT`` in fields of 10, for a :class:`~jaxfric.contact.friction.VelocityDecay` (FS = mu_0, FD = mu_d,
  DC = decay; the rest blank: the code's defaults). LS-DYNA's contact friction has no pressure term, so a
  polynomial law has no LS-DYNA card here.
- CSV (:func:`friction_csv`): the coefficient against the contact pressure at one speed, for codes that
  take a table.

Units: p in MPa (N/mm^2), v in mm/s, so C1 in 1/MPa, C2 in s/mm, ..., DC in s/mm: a deck in mm, N and s.
"""

from __future__ import annotations

import numpy as np

from ..contact.friction import FrictionLaw, Polynomial, VelocityDecay
from .formats import _f10, _f20

__all__ = ["radioss_friction", "lsdyna_friction", "friction_csv"]


def radioss_friction(law: FrictionLaw, mu0: float, *, fric_id: int = 1, title: str = "jaxfric friction law") -> str:
    """The OpenRadioss ``/FRICTION`` block of a :class:`Polynomial` (``Ifric`` = 1) or :class:`VelocityDecay`
    (``Ifric`` = 4) ``law`` about the Coulomb (static) coefficient ``mu0`` (module doc)."""
    if isinstance(law, Polynomial):
        ifric, c = 1, [float(getattr(law, k)) for k in Polynomial.TERMS]
        formula = (f"mu = max({float(mu0):.6g} + {c[0]:.6g} p + {c[1]:.6g} v + {c[2]:.6g} p v + {c[3]:.6g} p^2 "
                   f"+ {c[4]:.6g} v^2, 0)")
    elif isinstance(law, VelocityDecay):
        ifric, c = 4, [float(law.mu_d), float(law.decay), 0.0, 0.0, 0.0]
        formula = f"mu = {c[0]:.6g} + ({float(mu0):.6g} - {c[0]:.6g}) exp(-{c[1]:.6g} v)"
    else:
        raise ValueError(f"field 'law': no OpenRadioss /FRICTION form for {type(law).__name__} here")
    lines = [
        f"# jaxfric: {formula}",
        "# p: contact pressure (MPa), v: sliding speed (mm/s); units mm, N, s",
        f"/FRICTION/{int(fric_id)}",
        title[:100],
        "#   I_fric   I_filtr              X_freq    I_form",
        _f10(ifric) + _f10(0) + " " * 20 + " " * 10,
        "#                 C1                  C2                  C3                  C4                  C5",
        "".join(_f20(v) for v in c),
        "#                 C6                FRIC               VIS_f",
        _f20(0.0) + _f20(mu0) + " " * 20,
    ]
    return "\n".join(lines) + "\n"


def lsdyna_friction(law: FrictionLaw, mu0: float) -> str:
    """Card 2 of an LS-DYNA ``*CONTACT_...`` keyword for a :class:`VelocityDecay` ``law`` about the static
    coefficient ``mu0`` (module doc), with its comment lines."""
    if not isinstance(law, VelocityDecay):
        raise ValueError(f"field 'law': LS-DYNA's contact friction takes a velocity decay only, not "
                         f"{type(law).__name__}")
    lines = [f"$ jaxfric: mu = {float(law.mu_d):.6g} + ({float(mu0):.6g} - {float(law.mu_d):.6g}) "
             f"exp(-{float(law.decay):.6g} v), v the sliding speed (mm/s); units mm, N, s",
             "$       FS        FD        DC        VC       VDC    PENCHK        BT        DT",
             "".join(_f10(float(v), digits=6) for v in (mu0, law.mu_d, law.decay))]
    return "\n".join(lines) + "\n"


def friction_csv(law: FrictionLaw, mu0: float, p_max: float, n: int = 41, v: float = 0.0) -> str:
    """The coefficient at ``n`` pressures from 0 to ``p_max`` (MPa) at speed ``v`` (mm/s), units in the header."""
    p = np.linspace(0.0, float(p_max), int(n))
    mu = np.asarray(law.coefficient(float(mu0), p, float(v)))
    rows = [f"# {law.describe()} about mu_0 = {float(mu0):.6g}, at v = {float(v):g} mm/s",
            "contact pressure (MPa),friction coefficient (-)"]
    rows += [f"{a:.10g},{b:.10g}" for a, b in zip(p, mu, strict=True)]
    return "\n".join(rows) + "\n"
