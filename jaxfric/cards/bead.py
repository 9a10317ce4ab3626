"""Equivalent drawbead data for stamping codes: the bead's forces per unit length against its penetration.

    >>> card = bead_card("shape3", penetrations=(0.25, 0.5, 0.75, 1.0))
    >>> card.restraining_force, card.normal_force        # N/mm, one entry per penetration (0 first)

A stamping simulation replaces a drawbead by a line that restrains the sheet drawn across it; its code
wants the restraining force and the normal (opening) force per unit bead length as functions of the
bead's penetration (LS-DYNA's ``*CONTACT_DRAWBEAD``; ``../shared/spec/drawbead_cards.md``). They come
from plane-strain runs of the bead: the blankholder scene with ``lock_control="depth"``, the male bead
closed to each penetration d (the lower tool's stroke from first contact, 0 < d <= H) and held there
while the sheet is pulled to a steady draw, without the lands' lock force (the binder's own friction
is the 3D model's contact). Per penetration:

- restraining force: the steady drawing force (N/mm); its bending-unbending part is the same run with
  mu = 0 (the frictionless bead), the friction part the difference;
- normal force: the steady force on the lower tool (N/mm), the bead's opening force;
- after the bead (the columns that started upstream of the groove and now lie over the downstream
  land): the sheet's thinning 1 - h / t from its current thickness h, and its equivalent plastic strain
  (mean over the columns' points, and the largest);
- with ``derivatives``: the derivatives of the restraining force, its bending part, the normal force and
  the thinning and plastic strain after the bead for config fields of the scene (geometry R, r, Rp, H,
  the sheet's t, friction mu, ...), by forward mode along each run's own step sequence
  (:func:`jaxfric.identification.params.path_function`; the bending part's from the frictionless run,
  zero for mu; the thinning's and plastic strain's from the final state, over the same columns).

Schedule [chosen]: every penetration closes in the same number of steps as the full depth does at the
scene's ``ds_close`` (so that all of them share one compiled program: the closure is a value, not
structure), then the sheet is pulled ``U_pull`` = max(35, floor(2 (x_g + r)) + 10) mm (:func:`card_pull`;
x_g the groove mouth's half-width, r its fillets' radius: 35, 46 and 58 mm for the 6, 9 and 12 mm beads)
with the steady window the last 10 mm: after
2 (x_g + r) of pull the sheet that lay on the upstream land has crossed the whole groove onto the
downstream land, where its thinning is read. Measured on shape1 at the spec mesh (``jaxfric run blankholder
--variant shape1 --algorithm lcp_ssn --set lock_control=depth``: full depth, a 55 mm pull): the drawing
force averages 147.68, 149.64, 149.85, 149.38 and 149.36 N/mm over U in [20, 25], [25, 30], [30, 35],
[35, 45] and [45, 55] mm, so its card's [25, 35] (149.74) gives the spec window's steady value (149.37)
within 0.3 %, inside the run's scatter estimate (0.85 %).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from .. import scenes
from ..identification.params import parameterize, path_function
from ..io.instants import steady_drawing_force, steady_rows
from ..loadpath.run import run
from ..numerics.results import Result, SimulationError
from ..scenes.blankholder import BlankholderConfig, groove_geometry

__all__ = ["BeadCard", "bead_card", "card_overrides", "card_pull", "DEFAULT_PENETRATIONS"]

DEFAULT_PENETRATIONS = (0.25, 0.5, 0.75, 1.0)  # fractions of the bead height H [chosen]
MIN_PULL, WINDOW = 35.0, 10.0                  # mm: the shortest pull, and the steady window's length [chosen]


@dataclasses.dataclass(frozen=True)
class BeadCard:
    """A bead's equivalent data per unit length, against its penetration (the first entry: 0, no contact).

    Attributes:
        variant: the blankholder variant (bead shape); ``overrides``: the config values set on it.
        depth: the bead's full depth H (mm): DBDTH of LS-DYNA, DEPTH of OpenRadioss.
        thickness: the sheet's thickness t (mm); ``mu``: its friction coefficient on the tools.
        penetration: (k,) mm. Every force below is N/mm (per unit bead length), (k,).
        restraining_force, bending_force: the steady drawing force, with friction and with mu = 0.
        normal_force, normal_force_bending: the steady force on the lower tool, likewise.
        scatter: the restraining force's standard deviation over the steady window (N/mm): the card's
            error estimate from the steady regime (the runs' discretisation error is not in it).
        thinning: 1 - h / t of the sheet after the bead (-); eqps_after, eqps_after_max: its equivalent
            plastic strain there, mean and largest.
        derivatives: {field: {output: (k,)}} per unit of the field, for the outputs
            ``restraining_force``, ``bending_force``, ``normal_force``, ``thinning``, ``eqps_after`` and
            ``eqps_after_max`` (empty without ``derivatives``; 0 at penetration 0, NaN where the thinning
            is).
        wall_s: the runs' solve time (s).
        notes: one line per run that the card's algorithm did not complete and the penalty law (with the
            step controller's damper) ran instead.
    """

    variant: str
    overrides: dict
    depth: float
    thickness: float
    mu: float
    penetration: np.ndarray
    restraining_force: np.ndarray
    bending_force: np.ndarray
    normal_force: np.ndarray
    normal_force_bending: np.ndarray
    scatter: np.ndarray
    thinning: np.ndarray
    eqps_after: np.ndarray
    eqps_after_max: np.ndarray
    derivatives: dict = dataclasses.field(default_factory=dict)
    wall_s: float = 0.0
    notes: tuple = ()

    @property
    def friction_force(self) -> np.ndarray:
        """The friction part of the restraining force, restraining - bending (N/mm)."""
        return self.restraining_force - self.bending_force


def _config(variant: str, algorithm: str, overrides: dict) -> BlankholderConfig:
    """The blankholder config of ``variant`` with ``overrides`` and the card's lock mode."""
    config = scenes.make("blankholder", variant, algorithm, {**overrides, "lock_control": "depth"}).config
    assert isinstance(config, BlankholderConfig)
    return config


def card_pull(config: BlankholderConfig) -> float:
    """The card's pull (mm): max(35, floor(2 (x_g + r)) + 10) (the module docstring)."""
    return max(MIN_PULL, math.floor(2.0 * (groove_geometry(config)["x_g"] + config.r)) + WINDOW)


def card_overrides(variant: str, penetration: float, overrides: dict | None = None,
                   config: BlankholderConfig | None = None) -> dict:
    """The blankholder overrides of one run of a card: the bead closed to ``penetration`` (mm) and held,
    the card's pull and window (where ``overrides`` do not set them), in the closing steps of the full
    depth (the module docstring). ``config``: the blankholder config of ``variant`` with ``overrides``
    (built here when not given; the friction fields do not enter)."""
    base = dict(overrides or {})
    config = _config(variant, "lcp_ssn", base) if config is None else config
    n_close = max(1, round(config.H / config.ds_close))
    pull = float(config.U_pull) if "U_pull" in base else card_pull(config)  # a given pull keeps its window
    out = {"U_pull": pull, "steady_window": (pull - WINDOW, pull), **base, "lock_control": "depth",
           "closure": float(penetration), "ds_close": float(penetration) / n_close}
    return out


def _after_bead_columns(scene, final) -> np.ndarray:
    """The node columns that started upstream of the groove (X < -x_g - r) and lie over the downstream land
    (x_g + r < x < x_g + L) at the end."""
    config, mesh = scene.config, scene.model.mesh
    groove = groove_geometry(config)
    columns, ny = mesh.n_stored_columns, mesh.ny
    nodes = np.asarray(mesh.nodes).reshape(columns, ny + 1, 2)
    x = nodes + np.asarray(final.u).reshape(columns, ny + 1, 2)
    X_mid, x_mid = nodes[:, ny // 2, 0], x[:, ny // 2, 0]
    # The corner columns only (every column of a bilinear mesh), so that a column names an element column too.
    return mesh.order * np.flatnonzero(((X_mid < -groove["x_g"] - config.r) & (x_mid > groove["x_g"] + config.r)
                                        & (x_mid < groove["x_g"] + config.L))[:mesh.n_columns:mesh.order])


def _after_bead_values(cols, nodes, u, eqps, t, nx: int, ny: int, order: int = 1):
    """Thinning 1 - h / t and the mean and largest eqps of the node columns ``cols`` (corner columns of a mesh
    of elements of ``order`` along the strip), from the reference nodes (n, 2), the displacements (n, 2) and
    the points' eqps (n_el, gp): NumPy or JAX arrays (the latter differentiated for the card's derivatives)."""
    x = (nodes + u).reshape(order * (nx + 1), ny + 1, 2)
    h = jnp.linalg.norm(x[cols, ny] - x[cols, 0], axis=-1)
    e = eqps.reshape(nx, ny, -1)[np.minimum(cols // order, nx - 1)]
    return 1.0 - jnp.mean(h) / t, jnp.mean(e), jnp.max(e)


def _after_bead(scene, final) -> tuple[float, float, float]:
    """Thinning, mean and largest eqps after the bead (:func:`_after_bead_columns`); NaN where no column has
    crossed the whole groove."""
    cols = _after_bead_columns(scene, final)
    if cols.size == 0:
        return math.nan, math.nan, math.nan
    mesh = scene.model.mesh
    values = _after_bead_values(cols, mesh.nodes, final.u, final.material.eqps, scene.config.t, mesh.nx, mesh.ny,
                                mesh.order)
    return tuple(float(v) for v in values)  # type: ignore[return-value]


def _steady(history: dict, window) -> tuple[float, float, float]:
    """Steady drawing force, its scatter (standard deviation) and the steady lower-tool force."""
    values = {"phase": history["phase_name"], "drawing_displacement": history["drawing_displacement"]}
    drawing = steady_drawing_force({**values, "drawing_force": history["drawing_force"]}, window)
    normal = steady_drawing_force({**values, "drawing_force": history["clamping_force"]}, window)
    if drawing is None or normal is None:
        raise ValueError(f"bead card: no steady window {window} mm in the run (raise U_pull)")
    rows = steady_rows(history["phase_name"], history["drawing_displacement"], window)
    return drawing, float(np.std(np.asarray(history["drawing_force"])[rows])), normal


DERIVED = ("restraining_force", "normal_force", "thinning", "eqps_after", "eqps_after_max")


def _derivatives(variant, algorithm, overrides, names, history, window, cols=None) -> dict:
    """d(steady restraining force, steady normal force) / d(config field), along the run's steps, and with
    ``cols`` (:func:`_after_bead_columns`, not empty) d(thinning, mean and largest eqps after the bead):
    {field: {output: value}} with the outputs of :data:`DERIVED`."""
    par = parameterize("blankholder", names, variant=variant, algorithm=algorithm, overrides=overrides)
    f = path_function(par, plan=history, final=cols is not None)
    u = np.asarray(history["drawing_displacement"])
    rows = steady_rows(history["phase_name"], u, window)
    du = np.diff(u[rows])
    mesh = par.scene.model.mesh

    def outputs(p):
        h, _, *end = f(p)
        out = []
        for name in ("drawing_force", "clamping_force"):
            v = h.observed[name][rows]
            out.append(jnp.sum(0.5 * (v[1:] + v[:-1]) * du) / (u[rows][-1] - u[rows][0]))
        if end:
            final, nodes = end
            t = p[list(names).index("t")] if "t" in names else par.scene.config.t
            out += list(_after_bead_values(cols, nodes, final.u, final.material.eqps, t, mesh.nx, mesh.ny, mesh.order))
        return jnp.stack(out)

    jac = np.asarray(jax.jacfwd(outputs)(jnp.asarray(par.p0)))
    return {n: dict(zip(DERIVED, (float(v) for v in jac[:, i]), strict=False)) for i, n in enumerate(names)}


def _run(scene, variant: str, overrides: dict, algorithm: str, notes: list, what: str):
    """One run of the card, and the algorithm that completed it: where ``algorithm`` stops (after the
    stabilised attempts of StepControl.stabilize, which every algorithm has) or crawls (StepControl.stall_steps),
    the penalty law (the spec's eps_n) takes its place and ``notes`` says so, with the stop's result code."""
    try:
        return run(scene.model, newton=scene.newton, control=scene.control, observe=scene.observe,
                   progress=False), algorithm
    except SimulationError as stop:
        if algorithm == "penalty":
            raise
        notes.append(f"{what}: {algorithm} stopped ({Result(int(stop.code)).name}, "
                     f"{' '.join(str(stop).split()[:8])} ...); penalty instead")
        fallback = scenes.make("blankholder", variant, "penalty", overrides)
        return run(fallback.model, newton=fallback.newton, control=fallback.control, observe=fallback.observe,
                   progress=False), "penalty"


def bead_card(variant: str = "shape1", *, penetrations: Sequence[float] = DEFAULT_PENETRATIONS,
              absolute: bool = False, overrides: dict | None = None, algorithm: str = "lcp_ssn",
              derivatives: Sequence[str] = (), progress: Callable[[str], None] | None = None,
              ready: Callable[[], None] | None = None) -> BeadCard:
    """The equivalent drawbead data of blankholder ``variant`` (module docstring).

    Args:
        variant: the bead shape (``shape1`` ... ``shape9``, spec Table 7).
        penetrations: where to run, as fractions of the bead height H in (0, 1] (``absolute``: in mm).
        overrides: config values of the blankholder (mesh, material, friction ``mu``, ``t``, geometry);
            ``lock_control``, ``closure`` and ``ds_close`` are the card's.
        algorithm: the contact algorithm of the runs.
        derivatives: config fields to differentiate the forces for (e.g. ``("R", "t", "mu")``).
        progress: called with one line per run.
        ready: called once the inputs are checked, before the first run (the command line creates its
            output directory there, so that bad input leaves none behind).

    Raises ValueError (one line, naming the field) for bad penetrations or overrides, and
    :class:`~jaxfric.numerics.results.SimulationError` where a run does not complete.
    """
    overrides = dict(overrides or {})
    for name in ("lock_control", "closure", "ds_close"):
        if name in overrides:
            raise ValueError(f"field 'overrides': '{name}' is set by the bead card; leave it out")
    config = _config(variant, algorithm, overrides)
    values = np.asarray(penetrations, dtype=np.float64).ravel()
    depths = values if absolute else values * config.H
    if values.size == 0 or not np.all(np.isfinite(depths) & (depths > 0) & (depths <= config.H * (1 + 1e-12))):
        raise ValueError(f"field 'penetrations' = {list(values)} is invalid: each must lie in (0, "
                         f"{'H = ' + format(config.H, 'g') + ' mm' if absolute else '1'}]")
    depths = np.minimum(np.sort(depths), config.H)
    for name in derivatives:
        if name not in {f.name for f in dataclasses.fields(config)}:
            raise ValueError(f"field 'derivatives': {name!r} is not a config field of the blankholder")
    if ready is not None:
        ready()
    frictions: list[tuple[float, dict]] = [(config.mu, {})] + ([(0.0, {"mu": 0.0})] if config.mu > 0 else [])
    rows: dict = {k: [0.0] for k in ("F", "Fb", "N", "Nb", "s", "thin", "e", "emax")}
    keys = (*DERIVED, "bending_force")
    derived: dict = {n: {k: [0.0] for k in keys} for n in derivatives}
    wall, notes = 0.0, []  # type: float, list[str]
    for d in depths:
        for mu, extra in frictions:
            run_over = card_overrides(variant, d, {**overrides, **extra}, config)
            scene = scenes.make("blankholder", variant, algorithm, run_over)
            if progress:
                progress(f"bead card {variant}: penetration {d:.4g} mm, mu = {mu:g}")
            result, used = _run(scene, variant, run_over, algorithm, notes, f"penetration {d:.4g} mm, mu = {mu:g}")
            wall += result.wall_s
            history = result.history
            force, scatter, normal = _steady(history, scene.steady_window)
            if mu == config.mu:
                thin, e, emax = _after_bead(scene, result.final)
                rows["F"].append(force)
                rows["N"].append(normal)
                rows["s"].append(scatter)
                rows["thin"].append(thin)
                rows["e"].append(e)
                rows["emax"].append(emax)
                if derivatives:
                    cols = _after_bead_columns(scene, result.final)
                    for n, dd in _derivatives(variant, used, run_over, tuple(derivatives), history,
                                              scene.steady_window, cols if cols.size else None).items():
                        for k in DERIVED:
                            derived[n][k].append(dd.get(k, math.nan))
                        if config.mu == 0.0:   # no frictionless run: the bending part is the run itself
                            derived[n]["bending_force"].append(0.0 if n == "mu" else dd["restraining_force"])
            if mu == 0.0:
                rows["Fb"].append(force)
                rows["Nb"].append(normal)
            if mu == 0.0 and config.mu > 0.0:
                # The bending part is the frictionless run's: its derivatives are that run's (zero for mu,
                # which the part does not contain).
                fields = tuple(n for n in derivatives if n != "mu")
                if fields:
                    for n, dd in _derivatives(variant, used, run_over, fields, history, scene.steady_window).items():
                        derived[n]["bending_force"].append(dd["restraining_force"])
                if "mu" in derivatives:
                    derived["mu"]["bending_force"].append(0.0)
    arr = {k: np.asarray(v) for k, v in rows.items()}
    return BeadCard(variant=variant, overrides=overrides, depth=float(config.H), thickness=float(config.t),
                    mu=float(config.mu), penetration=np.concatenate([[0.0], depths]),
                    restraining_force=arr["F"], bending_force=arr["Fb"], normal_force=arr["N"],
                    normal_force_bending=arr["Nb"], scatter=arr["s"], thinning=arr["thin"], eqps_after=arr["e"],
                    eqps_after_max=arr["emax"],
                    derivatives={n: {k: np.asarray(v) for k, v in d.items()} for n, d in derived.items()},
                    wall_s=wall, notes=tuple(notes))
