"""Command line: ``jaxfric scenes`` and ``jaxfric run SCENE ...`` (outputs spec section 1).

    jaxfric scenes
    jaxfric run nine --variant mu017 --algorithm auglag --mesh 150x3 --set U_draw=40 --out runs/x

``run`` builds the scene (:func:`jaxfric.scenes.make`), runs it with a progress bar, writes the run
directory (:func:`jaxfric.output.write_run`) and prints where the files are, the steady drawing force,
and the solve and compile times. Exit status: 0 on success, 1 when the run stopped early or its files
could not all be written (what converged is still written), 2 for bad input. Errors are one line on
stderr, without traceback.
"""

from __future__ import annotations

import argparse
import os
import sys

__all__ = ["main", "build_parser", "UsageError"]

ALGORITHMS = ("penalty", "auglag", "lcp_lemke", "lcp_ssn")
EXIT_OK, EXIT_FAILED, EXIT_USAGE = 0, 1, 2


class UsageError(Exception):
    """Bad command-line input (reported as one line, exit status 2)."""


class _Parser(argparse.ArgumentParser):
    """argparse that raises instead of printing the usage and exiting."""

    def error(self, message):
        raise UsageError(message)


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
    run.add_argument("--variant", help="scene variant (default: the scene's first)")
    run.add_argument("--algorithm", default="penalty", help=f"one of {', '.join(ALGORITHMS)} (default penalty)")
    run.add_argument("--mesh", metavar="NXxNY", help="elements along x and through the thickness, e.g. 300x3")
    run.add_argument("--set", dest="overrides", action="append", default=[], metavar="NAME=VALUE",
                     help="override a config field (repeatable); see 'jaxfric scenes'")
    run.add_argument("--out", metavar="DIR", help="run directory (default runs/SCENE/VARIANT/ALGORITHM)")
    run.add_argument("--tag", help="study tag recorded in summary.json (regex [A-Za-z0-9][A-Za-z0-9._+-]*)")
    run.add_argument("--quiet", action="store_true", help="no progress bar")
    # Room for later subcommands: "report" (tables and figures over run directories) and "fit".
    return parser


def _one_line(text) -> str:
    return " ".join(str(text).split())


def _error(message: str, code: int) -> int:
    print(f"jaxfric: error: {_one_line(message)}", file=sys.stderr)
    return code


def main(argv=None) -> int:
    """Entry point of the ``jaxfric`` console script; returns the exit status."""
    parser = build_parser()
    try:
        args = parser.parse_args(sys.argv[1:] if argv is None else list(argv))
    except UsageError as err:
        return _error(err, EXIT_USAGE)
    except SystemExit as done:  # --help
        return int(done.code or 0)
    if args.command is None:
        parser.print_help()
        return EXIT_USAGE
    try:
        if args.command == "scenes":
            return _scenes()
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


def _build(args):
    """The scene of the command line; bad input -> UsageError naming it."""
    import re

    from . import scenes

    if args.scene not in scenes.scene_names():
        raise UsageError(f"unknown scene {args.scene!r}; choose one of {', '.join(scenes.scene_names())}")
    if args.variant is not None and args.variant not in scenes.variants(args.scene):
        raise UsageError(f"unknown variant {args.variant!r} of scene {args.scene!r}; choose one of "
                         f"{', '.join(scenes.variants(args.scene))}")
    if args.algorithm not in ALGORITHMS:
        raise UsageError(f"unknown algorithm {args.algorithm!r}; choose one of {', '.join(ALGORITHMS)}")
    if args.tag is not None and not re.fullmatch(r"[A-Za-z0-9][A-Za-z0-9._+-]*", args.tag):
        raise UsageError(f"--tag {args.tag!r} must match [A-Za-z0-9][A-Za-z0-9._+-]*")
    overrides = _overrides(args.overrides)
    if "mesh" in overrides and args.mesh is not None:
        raise UsageError("give the mesh either with --mesh or with --set mesh=..., not both")
    try:
        if args.mesh is not None:
            overrides["mesh"] = "x".join(str(v) for v in scenes.parse_mesh(args.mesh))
        for field, value in overrides.items():
            if field != "mesh":
                scenes.parse_override(args.scene, field, value)  # names the bad field / value
        return scenes.make(args.scene, args.variant, args.algorithm, overrides)
    except (ValueError, TypeError) as err:
        raise UsageError(str(err)) from None


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


def _run(args) -> int:
    scene = _build(args)
    from . import output
    from .run import run

    out = os.path.join("runs", scene.name, scene.variant, scene.algorithm) if args.out is None else args.out
    _writable_dir(out)
    label = f"{scene.name}/{scene.variant}/{scene.algorithm} "
    result = run(scene.model, control=scene.control, observe=scene.observe, snapshot=scene.snapshot,
                 progress=not args.quiet, raise_on_failure=False, label=label)
    try:
        summary = output.write_run(scene, result, out, tag=args.tag)
    except output.OutputError as err:
        return _error(err, EXIT_FAILED)
    steady = summary["steady_drawing_force"]
    a, b = summary["steady_window"]
    print(f"run directory: {out}")
    print("figures: " + ", ".join(os.path.join(out, f) for f in ("forces.png", "contact.png", "mesh.png")))
    print(f"steady drawing force: {'n/a' if steady is None else f'{steady:.6g} N/mm'} "
          f"(window U in [{a:g}, {b:g}] mm)")
    print(f"steps {summary['n_steps']}, Newton iterations {summary['newton_iters_total']}, "
          f"cutbacks {summary['n_cutbacks']}; solve {summary['wall_s']:.2f} s, compile "
          f"{summary['compile_s']:.2f} s")
    est = summary["error_estimate"]
    print(f"wall time {summary['wall_s'] + summary['compile_s']:.2f} s; error estimate of the "
          f"{est['quantity'].replace('_', ' ')}: +/- {est['absolute']:.3g} N/mm ({100 * est['relative']:.2g} %; "
          + ", ".join(f"{k} {100 * v:.2g} %" for k, v in est["components"].items()) + ")")
    if not summary["converged"]:
        return _error(f"run did not complete (partial results written to {out}): {summary['message']}",
                      EXIT_FAILED)
    if summary["message"]:
        print(f"note: {summary['message']}")
    return EXIT_OK


if __name__ == "__main__":
    sys.exit(main())
