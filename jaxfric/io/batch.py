"""Running many cases into run directories, resumably (the studies and the accuracy-cost report).

A case is an ordinary :func:`jaxfric.loadpath.run.run` written by :func:`jaxfric.io.output.write_run` into its own
directory. A directory that already holds a ``summary.json`` is read back instead of recomputed (unless
``rerun``), so an interrupted study resumes where it stopped, and a case that fails keeps its partial
run directory with the reason in ``summary.json`` ``message``. A case still running keeps a checkpoint in
its directory (``checkpoint.npz``, every :data:`CHECKPOINT_EVERY_S` s): a study killed in the middle of a
case (a time limit's SIGTERM, Ctrl-C, a crash) continues that case from it, bit for bit the run that never
stopped, so a case of hours can run over several sittings.
"""

from __future__ import annotations

import csv
import hashlib
import json
import math
import os
import time

import numpy as np

__all__ = ["CHECKPOINT_EVERY_S", "case_configuration", "read_history", "phase_curve", "matching_rows",
           "replay_steps", "run_case", "stale", "write_csv"]

#: The shortest interval between two checkpoints of a running case (s; longer where writing one takes
#: over 1 % of it). A case killed while it runs loses at most one interval of its solve.
CHECKPOINT_EVERY_S = 60.0


def read_history(path: str) -> dict:
    """``history.csv`` as a dict of NumPy columns (``phase`` as strings); {} for an empty file."""
    with open(path, newline="") as fh:
        rows = list(csv.DictReader(fh))
    if not rows:
        return {}
    return {k: (np.array([r[k] for r in rows]) if k == "phase" else np.array([float(r[k]) for r in rows]))
            for k in rows[0]}


def phase_curve(history: dict, x_name: str, y_name: str, phase: str, start: bool = False):
    """(x, y) of the rows of ``phase``, sorted by x, or None if the phase has fewer than two rows. With
    ``start``, the row before the phase (the state it starts from) comes first: two runs with different
    first increments then share the phase's starting point instead of one curve being extrapolated."""
    sel = np.asarray(history["phase"] == phase)
    if sel.sum() < 2:
        return None
    first = int(np.argmax(sel))
    if start and first > 0:
        sel = sel.copy()
        sel[first - 1] = True
    x, y = history[x_name][sel], history[y_name][sel]
    order = np.argsort(x, kind="stable")
    return x[order], y[order]


def run_case(out: str, scene_name: str, variant: str | None, algorithm: str, overrides: dict, *,
             rerun: bool = False, progress: bool = False, figures: bool = False, tag: str | None = None,
             log=print, rerun_stale: bool = True, steps=None, checkpoint_s: float = CHECKPOINT_EVERY_S) -> dict:
    """Run one case into ``out`` (or read it back) and return ``{"summary", "history", "contact", "dir"}``.

    ``summary`` always has ``converged`` and ``message``: a case that could not even be built or run
    enters with ``converged`` False and the reason (one failed case never stops a batch). A run on
    disk made with another variant, algorithm or overrides (:func:`stale`) is run again, unless
    ``rerun_stale`` is False (read-only callers), which reads it back as it is.

    ``steps``: the end times of the steps to take (global pseudo-time, increasing, the last one the
    number of phases), for example another run's accepted steps (its history's ``time`` without the
    first row); they replace the scene's nominal increments (:func:`replay_steps`). The stale check
    does not compare them: a run directory made with other steps is read back as it is.

    A running case writes its checkpoint into ``out`` every ``checkpoint_s`` seconds (none in its first
    ``checkpoint_s``); a case without ``summary.json`` whose checkpoint has this case's configuration
    (:func:`case_configuration`) continues from it (unless ``rerun``), and the checkpoint is removed once
    ``summary.json`` is written. The resumed case's ``wall_s`` and ``cpu_s`` include the solve before the
    stop; its ``compile_s`` is the last process's.
    """
    from .. import scenes
    from ..loadpath.run import run
    from . import checkpoint, output
    from .instants import InstantRows

    path = os.path.join(out, "summary.json")
    changed = None if rerun or not os.path.exists(path) else stale(path, overrides, variant, algorithm)
    if changed:
        log(f"{out}: the run on disk has {changed}" + (": rerun" if rerun_stale else " (read back as it is)"))
    if rerun or (changed and rerun_stale) or not os.path.exists(path):
        t0 = time.perf_counter()
        log(f"{out}: {scene_name}/{variant}/{algorithm} {overrides}")
        try:
            scene = scenes.make(scene_name, variant, algorithm, dict(overrides))
            if steps is not None:
                scene = replay_steps(scene, steps)
            config = case_configuration(scene, steps)
            saved = None if rerun else _saved_checkpoint(out, scene, config, log)
            os.makedirs(out, exist_ok=True)
            keep = checkpoint.Every(lambda partial: checkpoint.save(out, partial.checkpoint, config), checkpoint_s,
                                    first_s=checkpoint_s)
            result = run(scene.model, newton=scene.newton, control=scene.control, observe=scene.observe,
                         snapshot=scene.snapshot, keep_snapshots=InstantRows(scene.name), resume=saved,
                         on_chunk=keep, progress=progress, raise_on_failure=False,
                         label=f"{os.path.basename(out)} ")
            output.write_run(scene, result, out, tag=tag, figures=figures)
        except output.OutputError as err:  # partial run directory; the reason is in summary.json
            log(f"{out}: {err}")
        except Exception as err:  # noqa: BLE001 - recorded as a failed case
            os.makedirs(out, exist_ok=True)
            message = f"{type(err).__name__}: {err}"
            with open(path, "w") as fh:
                json.dump({"converged": False, "message": message, "scene": scene_name, "variant": variant,
                           "algorithm": algorithm, "overrides": output.json_ready(overrides)},
                          fh, indent=2)
            log(f"{out}: failed: {message}")
        if os.path.exists(os.path.join(out, checkpoint.FILE)):  # summary.json written: nothing to resume
            os.remove(os.path.join(out, checkpoint.FILE))
        log(f"{out}: done in {time.perf_counter() - t0:.1f} s")
    with open(path) as fh:
        summary = json.load(fh)
    hist = os.path.join(out, "history.csv")
    npz = os.path.join(out, "contact.npz")
    return {"summary": summary, "history": read_history(hist) if os.path.exists(hist) else {},
            "contact": dict(np.load(npz, allow_pickle=False)) if os.path.exists(npz) else {}, "dir": out}


def case_configuration(scene, steps=None) -> dict:
    """What a case's checkpoint must share with the case that resumes from it: the scene's configuration
    (:func:`jaxfric.io.checkpoint.configuration`) and the digest of the steps it replays (None: the
    scene's own increments)."""
    from .checkpoint import configuration

    digest = None if steps is None else hashlib.sha256(np.ascontiguousarray(steps, float).tobytes()).hexdigest()
    return {**configuration(scene), "steps": digest}


def _saved_checkpoint(out: str, scene, config: dict, log):
    """The checkpoint that a case stopped while running left in ``out`` (:func:`run_case`), or None: none
    there, or one that does not fit this case (other settings or model), which is then run from the start."""
    from . import checkpoint

    if not os.path.exists(os.path.join(out, checkpoint.FILE)):
        return None
    try:
        saved, saved_config = checkpoint.load(out, scene)
    except (OSError, ValueError) as err:
        log(f"{out}: its checkpoint cannot be resumed ({err}): run from the start")
        return None
    diff = checkpoint.configuration_difference(saved_config, config)
    if diff is not None:
        log(f"{out}: its checkpoint is of another case ({diff}): run from the start")
        return None
    log(f"{out}: resumed from its checkpoint at step {saved.record.n_rows - 1}, "
        f"t = {float(saved.path.state.time):.6g}")
    return saved


def matching_rows(t_a, t_b, tol: float = 1e-9) -> tuple[np.ndarray, np.ndarray]:
    """Indices ``(ia, ib)`` of the rows of two runs' increasing ``time`` columns that end at the same
    pseudo-time (within ``tol``): where two step sequences meet, e.g. a run and its replay that cut some
    steps."""
    t_a, t_b = np.asarray(t_a, float), np.asarray(t_b, float)
    k = np.clip(np.searchsorted(t_b, t_a - tol), 0, len(t_b) - 1)
    hit = np.abs(t_b[k] - t_a) < tol
    return np.flatnonzero(hit), k[hit]


def replay_steps(scene, times):
    """``scene`` with its nominal increments replaced by steps ending at ``times`` (global
    pseudo-time; a step ending in (k, k + 1] belongs to phase k): :func:`jaxfric.fem.loading.with_steps`.
    The step controller still cuts a step that fails and grows back to the given steps, never beyond."""
    import dataclasses

    import equinox as eqx

    from ..fem.loading import with_steps

    times = np.asarray(times, float)
    phase = np.ceil(times - 1e-9).astype(int) - 1
    model = eqx.tree_at(lambda m: m.phases, scene.model, with_steps(scene.model.phases, times, phase))
    return dataclasses.replace(scene, model=model)


def _same(have, want) -> bool:
    """Whether a recorded value ``have`` (as summary.json stores it) is the requested ``want``."""
    if isinstance(want, (tuple, list)):
        return isinstance(have, list) and len(have) == len(want) and all(map(_same, have, want))
    if isinstance(have, bool) or isinstance(want, bool):
        return str(have).lower() == str(want).lower()
    if isinstance(have, (int, float)) and isinstance(want, str):
        try:
            want = float(want)
        except ValueError:
            return False
    if isinstance(want, float) and not math.isfinite(want):
        return have is None or have == want  # summary.json stores non-finite numbers as null
    if isinstance(have, (int, float)) and isinstance(want, (int, float)):
        return math.isclose(float(have), float(want), rel_tol=1e-12, abs_tol=0.0)
    return have == want


def stale(path: str, overrides: dict, variant: str | None = None, algorithm: str | None = None) -> str | None:
    """How the run recorded in ``path`` (a summary.json) differs from the requested ``variant``,
    ``algorithm`` (None: not compared) and ``overrides`` (``"mesh"`` as ``NXxNY`` or a pair, other keys
    config fields; a key that is no field of the scene's config is not compared, and a field the
    recorded config lacks, added since the run, is compared with its default, with which the run was
    made), or None when it does not. Where the summary names its scene and variant, the recorded fields
    that are not requested are compared too, with the variant's value or today's default: a run made
    before a default changed is not read back as a run at the new default. A failed case's summary
    records its overrides, which must then be the same keys and values."""
    from ..scenes import config_fields, parse_mesh, scene_names, variant_values, variants

    with open(path) as fh:
        summary = json.load(fh)
    for key, want in (("variant", variant), ("algorithm", algorithm)):
        if want is not None and summary.get(key) is not None and summary[key] != want:
            return f"{key} {summary[key]!r}, not {want!r}"
    wanted = dict(overrides)
    config = (summary.get("parameters") or {}).get("config")
    if config is None and "overrides" in summary:  # a failed case
        recorded = summary["overrides"]
        if set(recorded) != set(wanted):
            return f"overrides {sorted(recorded)}, not {sorted(wanted)}"
        config = recorded
    elif "mesh" in wanted:
        try:
            nx, ny = parse_mesh(wanted.pop("mesh"))
        except ValueError:
            return "another mesh"  # the request cannot be the run's
        wanted.update(nx=nx, ny=ny)
    scene = summary.get("scene")
    defaults = {f[0]: f[1] for f in config_fields(scene)} if scene in scene_names() else {}
    if defaults and config is not None and "overrides" not in summary and summary.get("variant") in variants(scene):
        expected = {**defaults, **variant_values(scene, summary["variant"])}
        wanted = {**{k: expected[k] for k in config if k in expected}, **wanted}
    for key, value in wanted.items():
        if config is None or (key not in config and key not in defaults):
            continue
        have = config[key] if key in config else defaults[key]
        if not _same(have, value):
            return f"{key} = {have!r}, not {value!r}"
    return None


def write_csv(path: str, rows: list[dict]) -> str:
    """Rows (dicts, union of their keys as header, None as an empty field) to ``path``."""
    os.makedirs(os.path.dirname(path) or ".", exist_ok=True)
    fields = list(dict.fromkeys(k for r in rows for k in r))
    # Written aside and moved into place: a reader (another process's report) never sees half a file.
    tmp = f"{path}.{os.getpid()}.tmp"
    with open(tmp, "w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=fields, restval="")
        writer.writeheader()
        writer.writerows([{k: ("" if v is None else v) for k, v in r.items()} for r in rows])
    os.replace(tmp, path)
    return path
