"""Command line: ``jaxfric scenes``, ``jaxfric run SCENE ...`` (outputs spec section 1),
``jaxfric fit SCENE --data CSV --param NAMES ...`` (:mod:`jaxfric.identification.fit`) and
``jaxfric design SCENE --target N_PER_MM --param NAMES --bounds ...`` (:mod:`jaxfric.identification.design`).

    jaxfric scenes
    jaxfric run nine --variant mu017 --algorithm auglag --mesh 150x3 --set U_draw=40 --out runs/x
    jaxfric fit nine --data runs/x/history.csv --param mu --mesh 100x2 --set U_draw=10 --set mu=0.12
    jaxfric design blankholder --variant shape3 --target 165 --param R,H --bounds R=3:9 --bounds H=6:9.7

``run`` builds the scene (:func:`jaxfric.scenes.make`), runs it with a progress bar, writes the run
directory (:func:`jaxfric.io.output.write_run`) and prints where the files are, the steady drawing force,
and the solve and compile times. The run directory is rewritten as the run goes (the data files every
few seconds, with ``summary.json`` saying ``converged: false`` and where the run stands, and
``checkpoint.npz``); SIGINT or SIGTERM stops the run after its current chunk of steps (about a second),
writes everything converged and says how to resume (``--resume DIR``); a second SIGINT stops at once.
Exit status: 0 on success, 1 when the run stopped early or its files could not all be written (what
converged is still written), 2 for bad input, 3 when a stop request ended the run. Errors are one line
on stderr, without traceback. ``run``, ``fit``, ``design`` and ``report`` keep their compiled programs in JAX's
persistent compilation cache (:mod:`jaxfric.io.cache`: ``~/.cache/jaxfric/xla``; ``JAXFRIC_CACHE_DIR=off``
turns it off), so a second run of the same configuration in a new process compiles nothing, and ask XLA for
its faster-compiling code generation (:mod:`jaxfric.io.xla_flags`; ``JAXFRIC_XLA_DEFAULTS=1`` keeps XLA's
defaults).
"""

from __future__ import annotations

import argparse
import os
import shlex
import shutil
import signal
import sys
from typing import Any

from .contact.formulations import ALGORITHMS

__all__ = ["main", "build_parser", "UsageError", "parse_grid"]

EXIT_OK, EXIT_FAILED, EXIT_USAGE, EXIT_STOPPED = 0, 1, 2, 3

#: The shortest interval between two writes of a running run's data files and checkpoint (s); longer
#: when a write costs more than 1 % of it. A stop request (SIGINT, SIGTERM) writes everything at once; only
#: a process killed outright loses the steps since the last write.
WRITE_INTERVAL_S = 10.0


class UsageError(Exception):
    """Bad command-line input (reported as one line, exit status 2)."""


class _Parser(argparse.ArgumentParser):
    """argparse that raises instead of printing the usage and exiting."""

    def error(self, message):
        raise UsageError(message)


class _Once(argparse.Action):
    """Store the value of an option that may be given once: a repeated option is refused, not
    silently replaced by its last value."""

    def __call__(self, parser, namespace, values, option_string=None):
        given = namespace.__dict__.setdefault("_given", {})
        if self.dest in given:
            raise argparse.ArgumentError(self, f"given twice ({given[self.dest]!r} and {values!r})")
        given[self.dest] = values
        setattr(namespace, self.dest, values)


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="jaxfric", description="Differentiable 2D FE simulator of sheet-metal "
                                                 "tribology benchmarks.")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)
    sub.add_parser("scenes", help="list scenes, variants and config fields (defaults, units)",
                   description="List the scenes, their variants and config fields with defaults and units.")
    run = sub.add_parser("run", help="run one scene variant and write its run directory",
                         description="Run one scene variant and write its run directory "
                                     "(history.csv, summary.json, contact.npz, forces/contact/mesh.png).")
    run.add_argument("scene", help="flat_die, bead, nine or blankholder")
    run.add_argument("--variant", action=_Once, help="scene variant (default: the scene's first)")
    # Exact contact by default: no gap, no penalty to choose, and the cheapest run on the Nine and
    # blankholder scenes; ``fit`` too, whose derivatives it gives by the implicit function theorem.
    run.add_argument("--algorithm", action=_Once, default="lcp_ssn",
                     help=f"one of {', '.join(ALGORITHMS)} (default lcp_ssn)")
    run.add_argument("--mesh", action=_Once, metavar="NXxNY",
                     help="elements along x and through the thickness, e.g. 300x3")
    run.add_argument("--set", dest="overrides", action="append", default=[], metavar="NAME=VALUE",
                     help="override a config field (repeatable); see 'jaxfric scenes'")
    run.add_argument("--out", action=_Once, metavar="DIR", help="run directory (default runs/SCENE/VARIANT/ALGORITHM)")
    run.add_argument("--resume", action=_Once, metavar="DIR",
                     help="continue the stopped run in DIR from its last checkpoint (same scene, variant, "
                          "algorithm and settings, except a longer stroke, which extends a stopped or "
                          "finished run; the run directory stays DIR)")
    run.add_argument("--tag", action=_Once,
                     help="study tag recorded in summary.json (regex [A-Za-z0-9][A-Za-z0-9._+-]*)")
    run.add_argument("--quiet", action="store_true", help="no progress bar")
    run.add_argument("--error-estimate", action=_Once, type=_estimates, default=(), metavar="WHAT",
                     help="basic (default): from the run's penetration, force scatter and Newton tolerance "
                          "(not the discretisation's error); or a comma list of: step (the run again with half "
                          "the nominal increments, or half the target of --set step_error, about twice the "
                          "cost), mesh (on half the elements along the "
                          "strip, about half the cost; overstates the error where that mesh is coarse) or "
                          "mesh_fine (on twice the elements, two to three times the cost; within 1 to 2 times "
                          "the error where it halves per halving), layers (twice the layers, about twice the "
                          "cost), sensitivity (penalty only: eps_N dF/d eps_N by forward mode, about one more "
                          "run); e.g. step,mesh_fine,layers")
    fit = sub.add_parser("fit", help="identify parameters from a measured drawing-force curve",
                         description="Fit scene config values (e.g. mu, R1) to a measured drawing-force curve "
                                     "(CSV with drawing_displacement and drawing_force; a history.csv of "
                                     "'jaxfric run' is valid) by bounded least squares; writes fit.json, "
                                     "fit_history.csv and fit.png.")
    fit.add_argument("scene", help="flat_die, bead, nine or blankholder")
    fit.add_argument("--data", action=_Once, required=True, metavar="CSV", help="measured curve")
    fit.add_argument("--param", action=_Once, required=True, metavar="NAME[,NAME...]",
                     help="config fields to fit, e.g. mu,R1")
    _model_arguments(fit, "fitted")
    fit.add_argument("--bounds", action="append", default=[], metavar="NAME=LOW:HIGH",
                     help="bounds of a fitted parameter (default [0, inf))")
    fit.add_argument("--grid", action="append", default=[], metavar="NAME=LOW:HIGH:N",
                     help="global stage: adaptive runs at N equally spaced values of NAME (every --grid "
                          "combined), least squares from the best interpolated point")
    fit.add_argument("--starts", action=_Once, type=int, default=1, metavar="K",
                     help="with --grid: least squares from the K lowest local minima of the "
                          "interpolated misfit, the best fit kept (default 1)")
    fit.add_argument("--window", action=_Once, type=float, metavar="MM",
                     help="fit the mean force over windows of this length instead of every point")
    fit.add_argument("--model-error", action=_Once, metavar="C[,C...]",
                     help="carry the model's discretisation error into the result: step, mesh and/or layers "
                          "(one adaptive run at the fitted values per component, that discretisation refined); "
                          "fit.json's model_error and a widened interval")
    fit.add_argument("--out", action=_Once, metavar="DIR", help="output directory (default fits/SCENE/VARIANT)")
    fit.add_argument("--quiet", action="store_true", help="no progress lines")
    des = sub.add_parser("design", help="tool dimensions for a target restraining force",
                         description="Find scene config values (a bead's R and H, the Nine's stroke or R1, the "
                                     "clamping force) within bounds for which the mean drawing force over the "
                                     "steady window meets a target (or the force meets a target curve), by "
                                     "bounded least squares on the forward-mode gradient; writes design.json, "
                                     "design_history.csv and design.png.")
    des.add_argument("scene", help="flat_die, bead, nine or blankholder")
    goal = des.add_mutually_exclusive_group(required=True)
    goal.add_argument("--target", action=_Once, type=float, metavar="N_PER_MM",
                      help="restraining force: the mean drawing force over the steady window (N/mm)")
    goal.add_argument("--target-curve", action=_Once, metavar="CSV",
                      help="target curve (drawing_displacement, drawing_force), as fit's --data")
    des.add_argument("--param", action=_Once, required=True, metavar="NAME[,NAME...]",
                     help="config fields to design, e.g. R,H; their start values are the variant's or --set's")
    des.add_argument("--bounds", action="append", default=[], metavar="NAME=LOW:HIGH",
                     help="bounds of every designed parameter (required)")
    _model_arguments(des, "designed")
    des.add_argument("--window", action=_Once, metavar="A:B or MM",
                     help="--target: the window A:B (mm) of the mean (default the scene's steady_window); "
                          "--target-curve: fit means over windows of MM instead of every point")
    des.add_argument("--rtol", action=_Once, type=float, default=1e-3,
                     help="the target is met within this relative tolerance (default 1e-3)")
    des.add_argument("--out", action=_Once, metavar="DIR", help="output directory (default designs/SCENE/VARIANT)")
    des.add_argument("--quiet", action="store_true", help="no progress lines")
    card = sub.add_parser("bead-card", help="equivalent drawbead data for stamping codes",
                          description="Run the blankholder's bead closed to several penetrations and drawn to a "
                                      "steady state, with and without friction, and write its restraining "
                                      "force (bending and friction components) and normal force per unit bead "
                                      "length against penetration, with the sheet's thinning and plastic "
                                      "strain after the bead: bead_card.k (LS-DYNA *CONTACT_DRAWBEAD and "
                                      "*DEFINE_CURVE), bead_card.rad (OpenRadioss /INTER/TYPE8), bead_card.csv, "
                                      "bead_card.json and bead_card.png (jaxfric.cards).")
    card.add_argument("--variant", action=_Once, default="shape1", help="bead shape, shape1 .. shape9 (default shape1)")
    card.add_argument("--algorithm", action=_Once, default="lcp_ssn",
                      help=f"one of {', '.join(ALGORITHMS)} (default lcp_ssn)")
    card.add_argument("--mesh", action=_Once, metavar="NXxNY", help="elements along x and through the thickness")
    card.add_argument("--set", dest="overrides", action="append", default=[], metavar="NAME=VALUE",
                      help="blankholder config field (repeatable): geometry, t, mu, material; see 'jaxfric scenes'")
    card.add_argument("--penetrations", action=_Once, default="0.25,0.5,0.75,1", metavar="F[,F...]",
                      help="penetrations as fractions of the bead height H, in (0, 1] (default 0.25,0.5,0.75,1)")
    card.add_argument("--derivatives", action=_Once, metavar="NAME[,NAME...]",
                      help="also the forces' derivatives for these config fields, e.g. R,mu")
    card.add_argument("--total", action="store_true",
                      help="LS-DYNA: LCIDRF is the whole restraining force and FS = FD = 0 (default: its "
                           "bending component, the contact adding FS times the normal force, FS = FD the bead "
                           "line's effective friction: the card's friction part over its normal force at full depth)")
    card.add_argument("--out", action=_Once, metavar="DIR", help="output directory (default cards/VARIANT)")
    card.add_argument("--quiet", action="store_true", help="no progress lines")
    report = sub.add_parser("report", help="studies across many runs (accuracy-cost)",
                            description="Error against run time: references, the sweep of algorithms, "
                                        "penalties, meshes and steps, Pareto plots and what to pick for "
                                        "10 %, 1 % and 0.1 % accuracy (jaxfric.identification.accuracy).")
    report.add_argument("which", choices=["accuracy-cost"], help="the report")
    report.add_argument("--quick", action="store_true", help="the small sweep (a few minutes)")
    report.add_argument("--test", action="append", default=None, metavar="NAME",
                        help="run only this test (repeatable), e.g. flat_die_const_force")
    report.add_argument("--out", action=_Once, metavar="DIR",
                        help="output directory (default runs/report/accuracy_cost, "
                             "with --quick runs/report/accuracy_cost_quick)")
    report.add_argument("--rerun", action="store_true", help="recompute runs already in DIR")
    report.add_argument("--quiet", action="store_true", help="no progress lines")
    return parser


ESTIMATES = ("sensitivity", "step", "mesh", "mesh_fine", "layers")


def _estimates(text: str) -> tuple:
    """``--error-estimate``: "basic" -> (); else the comma list of :data:`ESTIMATES`, each once, at most
    one of mesh and mesh_fine."""
    names = [w.strip() for w in text.split(",")]
    if names == ["basic"]:
        return ()
    bad = [n for n in names if n not in ESTIMATES]
    if bad or len(set(names)) != len(names) or {"mesh", "mesh_fine"} <= set(names):
        raise argparse.ArgumentTypeError(
            f"{text!r}: basic, or a comma list of {', '.join(ESTIMATES)} (each once, mesh or mesh_fine)")
    return tuple(names)


def _one_line(text) -> str:
    return " ".join(str(text).split())


def _causes(counts: dict) -> str:
    """The printed line's cutback causes: the steps cut per result code (summary.json ``cutback_causes``)."""
    if not counts:
        return ""
    return " (steps cut by " + ", ".join(f"{name} {n}" for name, n in counts.items()) + ")"


def _not_estimated(names) -> str:
    """The printed line's tail naming the discretisation components a run did not estimate, with the
    option that would."""
    if not names:
        return ""
    option = ",".join("mesh_fine" if n == "mesh" else n for n in names)
    words = names[0] if len(names) == 1 else ", ".join(names[:-1]) + " and " + names[-1]
    return f"; not estimated: {words} discretisation (--error-estimate {option})"


def _error(message: str | Exception, code: int) -> int:
    print(f"jaxfric: error: {_one_line(message)}", file=sys.stderr)
    return code


def main(argv=None) -> int:
    """Entry point of the ``jaxfric`` console script; returns the exit status."""
    parser = build_parser()
    argv = sys.argv[1:] if argv is None else list(argv)
    try:
        args = parser.parse_args(argv)
    except UsageError as err:
        return _error(err, EXIT_USAGE)
    except SystemExit as done:  # --help
        return int(done.code or 0)
    if args.command is None:
        parser.print_help()
        return EXIT_USAGE
    args.argv = argv
    try:
        if args.command == "scenes":
            return _scenes()
        from .io.cache import enable_compilation_cache
        from .io.xla_flags import host_devices, use_fast_compilation, use_host_cores

        if args.command == "run":
            use_host_cores()     # a run's work split over the process's cores (_run)
        use_fast_compilation()   # before the first computation: XLA reads its flags when it starts
        enable_compilation_cache()
        if args.command == "fit":
            return _fit(args)
        if args.command == "design":
            return _design(args)
        if args.command == "report":
            return _report(args)
        if args.command == "bead-card":
            return _bead_card(args)
        from .numerics.devices import run_devices

        with run_devices(host_devices()):   # the run and its companions, their work split over the cores
            return _run(args)
    except UsageError as err:
        return _error(err, EXIT_USAGE)


def _scenes() -> int:
    from . import scenes

    for name in scenes.scene_names():
        print(f"{name}")
        print(f"  variants: {', '.join(scenes.variants(name))}")
        print("  config fields (--set NAME=VALUE):")
        fields = scenes.config_fields(name)
        width = max(len(f[0]) for f in fields)
        for field, default, unit, doc in fields:
            shown = "None" if default is None else (",".join(f"{v:g}" for v in default)
                                                    if isinstance(default, tuple) else f"{default}")
            unit = "" if unit in ("", "-") else f" {unit}"
            print(f"    {field:<{width}}  {shown}{unit}  {doc}")
        print("    mesh (--mesh NXxNY)  sets nx and ny")
    print(f"algorithms: {', '.join(ALGORITHMS)}")
    return EXIT_OK


def _overrides(pairs) -> dict:
    """The --set NAME=VALUE pairs as {name: value text} (UsageError for a malformed pair or a name
    given twice)."""
    out = {}
    for text in pairs:
        name, sep, value = text.partition("=")
        name = name.strip()
        if not sep or not name:
            raise UsageError(f"--set expects NAME=VALUE, got {text!r}")
        if name in out:
            raise UsageError(f"--set gives field {name!r} twice")
        out[name] = value.strip()
    return out


def _check_scene_args(args):
    """Scene, variant and algorithm of the command line; bad input -> UsageError naming it."""
    from . import scenes

    if args.scene not in scenes.scene_names():
        raise UsageError(f"unknown scene {args.scene!r}; choose one of {', '.join(scenes.scene_names())}")
    if args.variant is not None and args.variant not in scenes.variants(args.scene):
        raise UsageError(f"unknown variant {args.variant!r} of scene {args.scene!r}; choose one of "
                         f"{', '.join(scenes.variants(args.scene))}")
    if args.algorithm not in ALGORITHMS:
        raise UsageError(f"unknown algorithm {args.algorithm!r}; choose one of {', '.join(ALGORITHMS)}")


def _build(args):
    """The scene of the command line; bad input -> UsageError naming it."""
    import re

    from . import scenes

    _check_scene_args(args)
    if args.tag is not None and not re.fullmatch(r"[A-Za-z0-9][A-Za-z0-9._+-]*", args.tag):
        raise UsageError(f"--tag {args.tag!r} must match [A-Za-z0-9][A-Za-z0-9._+-]*")
    overrides = _scene_overrides(args)
    try:
        return scenes.make(args.scene, args.variant, args.algorithm, overrides)
    except (ValueError, TypeError) as err:
        raise UsageError(str(err)) from None


def _scene_overrides(args) -> dict:
    """The --set and --mesh values parsed once into typed config overrides, as
    :func:`jaxfric.scenes.make` takes them: field -> value of the field's type, ``mesh`` -> (nx, ny)
    (:func:`jaxfric.scenes.parse_mesh`, where the mesh size is checked). Bad input -> UsageError
    naming the field or value."""
    from . import scenes

    texts = _overrides(args.overrides)
    if "mesh" in texts and args.mesh is not None:
        raise UsageError("give the mesh either with --mesh or with --set mesh=..., not both")
    try:
        mesh = None if args.mesh is None else scenes.parse_override(args.scene, "mesh", args.mesh)
        typed = {field: scenes.parse_override(args.scene, field, text) for field, text in texts.items()}
    except (ValueError, TypeError) as err:
        raise UsageError(str(err)) from None
    return typed if mesh is None else {**typed, "mesh": mesh}


def _writable_dir(out: str) -> None:
    """Create the run directory now, before the run, and prove it takes a file: an unwritable
    ``--out`` is bad input, not a failure after minutes of computing."""
    if not out.strip():
        raise UsageError("--out must name a directory, got an empty string")
    try:
        os.makedirs(out, exist_ok=True)
        probe = os.path.join(out, ".jaxfric-write-test")
        with open(probe, "w"):
            pass
        os.remove(probe)
    except OSError as err:
        raise UsageError(f"--out {out!r} is not a writable directory: {err.strerror or err}") from None
    except ValueError as err:  # e.g. an embedded null byte
        raise UsageError(f"--out {out!r} is not a valid path: {err}") from None


def _first_missing(path: str) -> str | None:
    """The outermost directory of ``path`` that does not exist yet (None if ``path`` exists)."""
    path = os.path.abspath(path)
    if os.path.exists(path):
        return None
    while not os.path.exists(os.path.dirname(path)) and os.path.dirname(path) != path:
        path = os.path.dirname(path)
    return path


class _StopRequest:
    """SIGINT and SIGTERM while a run goes: the first asks it to stop after its current chunk of steps;
    after it both signals take their default action, so a second one ends the process at once. Installed
    only in the main thread (elsewhere a signal cannot be caught)."""

    def __init__(self) -> None:
        self.signal: int | None = None
        self._previous: dict = {}

    def __enter__(self):
        try:
            self._previous = {s: signal.signal(s, self._handle) for s in (signal.SIGINT, signal.SIGTERM)}
        except ValueError:  # not the main thread
            self._previous = {}
        return self

    def __exit__(self, *exc):
        for s, handler in self._previous.items():
            signal.signal(s, handler)
        return False

    def _handle(self, signum, frame):
        self.signal = signum
        for s in self._previous:
            signal.signal(s, signal.SIG_DFL)
        print(f"\njaxfric: {signal.Signals(signum).name}: stopping after the current chunk of steps "
              f"(about a second); Ctrl-C again stops at once", file=sys.stderr, flush=True)

    def __call__(self) -> bool:
        return self.signal is not None


class _PartialWriter:
    """What a CLI run writes while it goes (:class:`jaxfric.io.checkpoint.Every` calls it after the first
    chunk and then every :data:`WRITE_INTERVAL_S` s at least): the run directory's data files and
    checkpoint, rewritten from the partial result."""

    def __init__(self, scene, out: str, tag, config: dict):
        self.scene, self.out, self.tag, self.config = scene, out, tag, config
        self.failed = False

    def __call__(self, result) -> None:
        from .io import output

        try:
            _write(self.scene, result, self.out, self.tag, self.config, figures=False)
        except (OSError, output.OutputError) as err:
            if not self.failed:
                print(f"note: the run directory could not be updated during the run: {_one_line(err)}",
                      file=sys.stderr)
            self.failed = True


def _write(scene, result, out: str, tag, config: dict, **options) -> dict:
    """The run directory of ``result`` (:func:`jaxfric.io.output.write_run` with ``options``) and its
    checkpoint; returns the summary."""
    from .io import checkpoint, output

    if result.checkpoint is not None:
        checkpoint.save(out, result.checkpoint, config)
    return output.write_run(scene, result, out, tag=tag, **options)


def _resume_command(argv: list, out: str) -> str:
    """The command line ``argv`` (without the program) that resumes this run from ``out``."""
    if "--resume" not in argv and not any(a.startswith("--resume=") for a in argv):
        argv = list(argv) + ["--resume", out]
    return "jaxfric " + " ".join(shlex.quote(a) for a in argv)


def _resume(args, scene, out: str):
    """The checkpoint to resume from (None without --resume): the saved one, or, when the command line
    asks for a longer stroke and nothing else differs, the saved one extended to it
    (:func:`jaxfric.loadpath.run.extend_stroke`). UsageError naming what does not fit."""
    if args.resume is None:
        return None
    import numpy as np

    from . import scenes
    from .io import checkpoint
    from .loadpath.run import extend_stroke

    try:
        saved, config = checkpoint.load(out, scene)
    except (OSError, ValueError) as err:
        raise UsageError(f"--resume {out}: {err}") from None
    field = scenes.SCENES[scene.name].STROKE_FIELD
    old, new = config["parameters"]["config"][field], float(getattr(scene.config, field))
    reference = scene
    if old != new:  # the same run but for its stroke?
        reference = scenes.make(scene.name, scene.variant, scene.algorithm, {**_scene_overrides(args), field: old})
    diff = checkpoint.configuration_difference(config, checkpoint.configuration(reference))
    if diff is not None:
        raise UsageError(f"--resume {out}: the configuration differs from the checkpoint's in {diff}; a run "
                         f"resumes with the settings it was started with (its stroke, {field}, may grow)")
    if old == new:
        return saved
    if new < old:
        raise UsageError(f"--resume {out}: {field} = {new:g} is shorter than the checkpoint's {old:g}; a stroke "
                         f"can only be extended")
    if not np.array_equal(np.asarray(reference.model.mesh.nodes), np.asarray(scene.model.mesh.nodes)):
        raise UsageError(f"--resume {out}: {field} = {new:g} moves this scene's mesh (its length follows the "
                         f"stroke); the run cannot be extended, only run again")
    return extend_stroke(saved, scene.model, old / new, control=scene.control)


def _run(args) -> int:
    scene = _build(args)
    from .io import checkpoint, output
    from .io.instants import InstantRows
    from .loadpath.run import MemoryBudgetError, run
    from .numerics.results import Result

    if "sensitivity" in args.error_estimate and scene.algorithm != "penalty":
        raise UsageError(f"--error-estimate sensitivity applies to algorithm penalty, not {scene.algorithm}")
    if args.resume is not None and args.out is not None and os.path.abspath(args.out) != os.path.abspath(args.resume):
        raise UsageError(f"--resume {args.resume} continues the run in that directory; --out {args.out} names another")

    out = args.resume or (os.path.join("runs", scene.name, scene.variant, scene.algorithm) if args.out is None
                          else args.out)
    resume = _resume(args, scene, out)
    created = _first_missing(out)
    _writable_dir(out)
    label = f"{scene.name}/{scene.variant}/{scene.algorithm} "
    config = checkpoint.configuration(scene)
    try:
        with _StopRequest() as stop:
            result = run(scene.model, newton=scene.newton, control=scene.control, observe=scene.observe,
                         snapshot=scene.snapshot, keep_snapshots=InstantRows(scene.name),
                         progress=not args.quiet, raise_on_failure=False, label=label, resume=resume,
                         on_chunk=checkpoint.Every(_PartialWriter(scene, out, args.tag, config), WRITE_INTERVAL_S),
                         stop=stop)
    except MemoryBudgetError as err:
        # Refused before it started: remove the directories made for it, if still empty.
        if created is not None and not any(files for _, _, files in os.walk(created)):
            shutil.rmtree(created, ignore_errors=True)
        raise UsageError(str(err)) from None
    # The optional components of the error estimate: write_run's arguments, computed from the finished run.
    extra: dict[str, Any] = {}
    if args.error_estimate and result.converged:
        from .identification import accuracy

        progress = not args.quiet
        companions = {
            "step": ("step", lambda: accuracy.step_check(scene, progress=progress)),
            "mesh": ("mesh", lambda: accuracy.mesh_check(scene, progress=progress)),
            "mesh_fine": ("mesh", lambda: accuracy.mesh_check(scene, progress=progress, finer=True)),
            "layers": ("layers", lambda: accuracy.layers_check(scene, progress=progress)),
        }
        for name in args.error_estimate:
            try:
                if name == "sensitivity":
                    extra["penalty_tangent"] = accuracy.penalty_tangent(scene, result)
                else:
                    component, compute = companions[name]
                    extra.setdefault("checks", {})[component] = compute()
            except ValueError as err:
                print(f"note: {err}")
    try:
        summary = _write(scene, result, out, args.tag, config, **extra)
    except (OSError, output.OutputError) as err:
        return _error(err, EXIT_FAILED)
    if result.code == Result.STOPPED:
        u = result.history.get("drawing_displacement")
        where = f"step {summary['n_steps']}, t = {float(result.final.time):.6g}" + (
            "" if u is None else f", drawing displacement {float(u[-1]):.6g} mm")
        print(f"jaxfric: stopped at {where}; results so far in {out}; resume with: "
              f"{_resume_command(args.argv, out)}", file=sys.stderr)
        return EXIT_STOPPED
    steady = summary["steady_drawing_force"]
    a, b = summary["steady_window"]
    print(f"run directory: {out}")
    print("figures: " + ", ".join(os.path.join(out, f) for f in ("forces.png", "contact.png", "mesh.png")))
    print(f"steady drawing force: {'n/a' if steady is None else f'{steady:.6g} N/mm'} "
          f"(window U in [{a:g}, {b:g}] mm)")
    print(f"steps {summary['n_steps']}, Newton iterations {summary['newton_iters_total']}, "
          f"cutbacks {summary['n_cutbacks']}{_causes(summary['cutback_causes'])}; solve {summary['wall_s']:.2f} s, "
          f"compile {summary['compile_s']:.2f} s")
    est = summary["error_estimate"]
    print(f"wall time {summary['wall_s'] + summary['compile_s']:.2f} s; error estimate of the "
          f"{est['quantity'].replace('_', ' ')}: +/- {est['absolute']:.3g} N/mm ({100 * est['relative']:.2g} %; "
          + ", ".join(f"{k} {100 * v:.2g} %" for k, v in est["components"].items()) + ")"
          + _not_estimated(est.get("not_estimated", [])))
    if not summary["converged"]:
        return _error(f"run did not complete (partial results written to {out}): {summary['message']}",
                      EXIT_FAILED)
    if summary["message"]:
        print(f"note: {summary['message']}")
    return EXIT_OK


def _bounds(pairs, names) -> dict:
    out = {}
    for text in pairs:
        name, sep, rng = text.partition("=")
        low, colon, high = rng.partition(":")
        name = name.strip()
        if not sep or not colon:
            raise UsageError(f"--bounds expects NAME=LOW:HIGH, got {text!r}")
        if name not in names:
            raise UsageError(f"--bounds names {name!r}, which --param does not fit ({', '.join(names)})")
        if name in out:
            raise UsageError(f"--bounds gives {name!r} twice")
        try:
            out[name] = (float(low), float(high))
        except ValueError:
            raise UsageError(f"--bounds {text!r}: LOW and HIGH must be numbers") from None
    return out


def parse_grid(specs, names) -> dict:
    """``--grid NAME=LOW:HIGH:N`` specs of the fitted parameters ``names`` -> {name: N values evenly
    spaced from LOW to HIGH}; bad input -> UsageError naming it."""
    from .identification.fit_global import MAX_GRID_POINTS

    out, points = {}, 1
    for text in specs:
        name, sep, rng = text.partition("=")
        parts = rng.split(":")
        name = name.strip()
        if not sep or len(parts) != 3:
            raise UsageError(f"--grid expects NAME=LOW:HIGH:N, got {text!r}")
        if name not in names:
            raise UsageError(f"--grid names {name!r}, which --param does not fit ({', '.join(names)})")
        if name in out:
            raise UsageError(f"--grid gives {name!r} twice")
        try:
            low, high, n = float(parts[0]), float(parts[1]), int(parts[2])
        except ValueError:
            raise UsageError(f"--grid {text!r}: LOW and HIGH must be numbers and N an integer") from None
        if not 2 <= n <= MAX_GRID_POINTS:
            raise UsageError(f"--grid {text!r}: N must be at least 2 and at most {MAX_GRID_POINTS}")
        points *= n
        if points > MAX_GRID_POINTS:
            raise UsageError(f"--grid: the grids combined give {points} runs, more than {MAX_GRID_POINTS}")
        out[name] = [low + (high - low) * k / (n - 1) for k in range(n)]
    return out


def _model_arguments(parser, what: str) -> None:
    """The scene model's options of ``fit`` and ``design`` (``what``: "fitted" or "designed")."""
    parser.add_argument("--variant", action=_Once, help="scene variant (default: the scene's first)")
    parser.add_argument("--algorithm", action=_Once, default="lcp_ssn",
                        help=f"one of {', '.join(ALGORITHMS)} (default lcp_ssn)")
    parser.add_argument("--mesh", action=_Once, metavar="NXxNY", help="elements along x and through the thickness")
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="NAME=VALUE",
                        help=f"override a config field; for a {what} field this is its start value")


def _parameters(args, folder: str) -> tuple[tuple, dict, dict, str, str]:
    """What ``fit`` and ``design`` share on the command line: the parameter names, the overrides, the
    bounds, the variant and the output directory (default ``folder/SCENE/VARIANT``)."""
    from . import scenes

    _check_scene_args(args)
    names = tuple(n.strip() for n in args.param.split(","))
    if not all(names):
        raise UsageError(f"--param expects NAME[,NAME...], got {args.param!r}")
    overrides = _scene_overrides(args)
    bounds = _bounds(args.bounds, names)
    variant = args.variant or scenes.default_variant(args.scene)
    out = os.path.join(folder, args.scene, variant) if args.out is None else args.out
    return names, overrides, bounds, variant, out


def _fit(args) -> int:
    from .identification.fit import FitError, fit, write_fit

    names, overrides, bounds, variant, out = _parameters(args, "fits")
    grid = parse_grid(args.grid, names)
    if not os.path.isfile(args.data):
        raise UsageError(f"--data {args.data!r} is not a file")
    try:
        # The output directory is made once fit() has validated the input, before its first simulation.
        result = fit(args.scene, args.data, names, variant=variant, algorithm=args.algorithm,
                     overrides=overrides, bounds=bounds, window=args.window, grid=grid or None,
                     starts=args.starts, progress=not args.quiet, ready=lambda: _writable_dir(out),
                     model_error=tuple(c.strip() for c in args.model_error.split(",")) if args.model_error else ())
    except ValueError as err:
        raise UsageError(str(err)) from None
    except FitError as err:
        return _error(f"fit failed: {err}", EXIT_FAILED)
    write_fit(result, out)
    print(f"fit directory: {out} (fit.json, fit_history.csv, fit.png)")
    for name in names:
        lo, hi = result.ci95[name]
        print(f"{name} = {result.params[name]:.8g} +/- {result.stderr[name]:.3g} (95 %: [{lo:.6g}, {hi:.6g}]; "
              f"start {result.start[name]:g})")
        if result.model_error is not None:
            lo, hi = result.ci95_model[name]
            print(f"  model's discretisation error: bias {result.model_error['bias'][name]:+.3g} ("
                  + ", ".join(f"{c} {v[name]:+.3g}" for c, v in result.model_error["components"].items())
                  + f"); 95 % with it: [{lo:.6g}, {hi:.6g}]")
    print(f"residual rms {result.residual_rms:.4g} N/mm over {result.n_points} "
          f"{'points' if result.window is None else 'windows'}; {result.n_simulations} simulations, "
          f"{result.wall_s:.1f} s")
    if not result.converged:
        return _error(f"fit did not converge (last values written to {out}): {result.message}", EXIT_FAILED)
    return EXIT_OK


def _design(args) -> int:
    import numpy as np

    from .identification.design import design, write_design
    from .identification.fit import FitError

    names, overrides, bounds, variant, out = _parameters(args, "designs")
    if args.target_curve is not None and not os.path.isfile(args.target_curve):
        raise UsageError(f"--target-curve {args.target_curve!r} is not a file")
    window = _design_window(args.window, args.target is not None)
    try:
        result = design(args.scene, args.target if args.target is not None else args.target_curve, names,
                        variant=variant, algorithm=args.algorithm, overrides=overrides, bounds=bounds, window=window,
                        rtol=args.rtol, progress=not args.quiet, ready=lambda: _writable_dir(out))
    except ValueError as err:
        raise UsageError(str(err)) from None
    except FitError as err:
        return _error(f"design failed: {err}", EXIT_FAILED)
    write_design(result, out)
    print(f"design directory: {out} (design.json, design_history.csv, design.png)")
    print(", ".join(f"{n} = {result.params[n]:.6g}" for n in names) + " (start "
          + ", ".join(f"{n} = {result.start[n]:g}" for n in names) + ")")
    if result.target is not None:
        print(f"restraining force {result.force:.6g} N/mm for a target of {result.target:.6g} "
              f"({100 * (result.force / result.target - 1):+.3g} %; start {result.start_value:.6g}); "
              + ", ".join(f"dF/d{n} = {v:.4g}" for n, v in result.sensitivity.items()))
    else:
        gap = float(np.max(np.abs(np.asarray(result.force) - result.targets)))
        print(f"largest difference from the target curve {gap:.4g} N/mm over {len(result.targets)} "
              f"{'points' if result.window is None else 'windows'}")
    print(f"{result.n_simulations} simulations, {result.wall_s:.1f} s")
    if not result.converged:
        return _error(f"design did not meet the target (last values written to {out}): {result.message}",
                      EXIT_FAILED)
    return EXIT_OK


def _design_window(text, scalar: bool):
    """``--window`` of ``design``: A:B (mm) for a restraining force, a length (mm) for a target curve."""
    if text is None:
        return None
    try:
        if scalar:
            a, colon, b = text.partition(":")
            if not colon:
                raise ValueError
            return float(a), float(b)
        return float(text)
    except ValueError:
        raise UsageError(f"--window expects {'A:B (mm)' if scalar else 'a length (mm)'}, got {text!r}") from None


def _bead_card(args) -> int:
    import numpy as np

    from .cards import bead_card, write_card
    from .numerics.results import SimulationError

    overrides = _overrides(args.overrides)
    if args.mesh is not None:
        overrides["mesh"] = args.mesh
    try:
        fractions = [float(v) for v in args.penetrations.split(",")]
    except ValueError:
        raise UsageError(f"--penetrations expects comma-separated fractions of H, got {args.penetrations!r}") from None
    names = tuple(n.strip() for n in args.derivatives.split(",")) if args.derivatives else ()
    out = os.path.join("cards", args.variant) if args.out is None else args.out
    try:
        card = bead_card(args.variant, penetrations=fractions, overrides=overrides, algorithm=args.algorithm,
                         derivatives=names, progress=None if args.quiet else print,
                         ready=lambda: _writable_dir(out))
    except ValueError as err:
        raise UsageError(str(err)) from None
    except SimulationError as err:
        return _error(f"bead card failed: {err}", EXIT_FAILED)
    paths = write_card(card, out, total=args.total)
    print(f"bead card directory: {out} ({', '.join(os.path.basename(p) for p in paths.values())})")
    print(f"at full depth {card.depth:g} mm: restraining force {card.restraining_force[-1]:.5g} N/mm (bending "
          f"{card.bending_force[-1]:.5g}, friction {card.friction_force[-1]:.5g}; scatter {card.scatter[-1]:.2g}), "
          f"normal force {card.normal_force[-1]:.5g} N/mm, " + (
              f"thinning {100 * card.thinning[-1]:.3g} %" if np.isfinite(card.thinning[-1]) else
              "thinning n/a (no sheet has passed the whole bead yet: a longer U_pull)"))
    for name, d in card.derivatives.items():
        print(f"d/d{name} at full depth: restraining {d['restraining_force'][-1]:.5g}, normal "
              f"{d['normal_force'][-1]:.5g} (N/mm per unit of {name})")
    for note in card.notes:
        print(f"note: {note}")
    print(f"{len(card.penetration) - 1} penetrations, solve {card.wall_s:.1f} s")
    return EXIT_OK


def _report(args) -> int:
    from .identification import accuracy, accuracy_report

    # The quick report has its own default folder: its test shares a name with the full report's.
    default = os.path.join("runs", "report", "accuracy_cost_quick" if args.quick else "accuracy_cost")
    out = default if args.out is None else args.out
    known = [t.name for t in (accuracy.QUICK_TESTS if args.quick else accuracy.TESTS)]
    for name in args.test or []:
        if name not in known:
            raise UsageError(f"--test {name!r} is not a test of this report; choose from {', '.join(known)}")
        if args.test.count(name) > 1:
            raise UsageError(f"--test {name!r} given twice")
    _writable_dir(out)
    log = (lambda m: None) if args.quiet else (lambda m: print(m, flush=True))
    rows = accuracy_report.accuracy_cost(out, quick=args.quick, tests=args.test, rerun=args.rerun,
                                         progress=not args.quiet, log=log)
    print(f"report: {os.path.join(out, 'accuracy_cost.md')}; table: {os.path.join(out, 'accuracy_cost.csv')}; "
          f"plots: {os.path.join(out, 'pareto_*.png')}")
    failed = [r for r in rows if not r["converged"]]
    if any(r["family"] == "reference" for r in failed):
        return _error("a reference run did not complete; its errors are missing (see the report)", EXIT_FAILED)
    if failed:
        print(f"note: {len(failed)} of {len(rows)} runs did not complete (listed in the report)")
    return EXIT_OK


if __name__ == "__main__":
    sys.exit(main())
