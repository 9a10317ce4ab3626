"""A run's checkpoint in its run directory (``checkpoint.npz``): what ``jaxfric run ... --resume DIR``
continues from.

One file, rewritten atomically (a temporary file renamed over it) so that a run killed while saving
leaves the previous checkpoint whole. It holds the load path's state between two chunks
(:class:`jaxfric.loadpath.run.Checkpoint`: its leaves in order, ``state/<k>``), the history rows so far
(``rows/<name>``, the observations ``observed/<name>``), the snapshots kept (``snapshot/<row>/<key>``)
and, as JSON (``meta``), the run's configuration, its solve and CPU times. A resumed run continues from
exactly these arrays, so it is the run that never stopped, bit for bit.
"""

from __future__ import annotations

import json
import os
import time
from typing import Any

import equinox as eqx
import jax
import numpy as np

from ..loadpath.run import Checkpoint, Record
from ..loadpath.simulate import begin
from .output import json_ready

__all__ = ["FILE", "Every", "configuration", "save", "load", "configuration_difference"]

FILE = "checkpoint.npz"


def configuration(scene) -> dict:
    """What a resumed run must share with the run it continues: the scene, the algorithm and the
    resolved parameters, as JSON reads them back."""
    return json.loads(json.dumps(json_ready({"scene": scene.name, "algorithm": scene.algorithm,
                                              "parameters": scene.parameters})))


def save(out_dir: str, checkpoint: Checkpoint, config: dict) -> str:
    """Write ``checkpoint`` with the run's ``config`` (:func:`configuration`) to
    ``out_dir/checkpoint.npz``; returns the path."""
    record = checkpoint.record
    cols = record.columns()
    leaves = jax.tree_util.tree_leaves(checkpoint.path)
    arrays: dict[str, Any] = {f"state/{k}": np.asarray(leaf) for k, leaf in enumerate(leaves)}
    arrays.update({f"rows/{k}": v for k, v in cols.items() if k != "observed"})
    arrays.update({f"observed/{k}": v for k, v in cols["observed"].items()})
    for row, snap in record.snapshots.items():
        arrays.update({f"snapshot/{row}/{k}": np.asarray(v) for k, v in snap.items()})
    meta = {"config": config, "wall_s": record.wall_s, "cpu_s": record.cpu_s,
            "band_widened": [list(w) for w in record.band_widened]}
    arrays["meta"] = np.array(json.dumps(meta, allow_nan=False))
    path = os.path.join(out_dir, FILE)
    tmp = os.path.join(out_dir, "checkpoint.tmp.npz")
    np.savez(tmp, **arrays)
    os.replace(tmp, path)
    return path


def load(out_dir: str, scene) -> tuple[Checkpoint, dict]:
    """The checkpoint in ``out_dir`` and its run's configuration, read for ``scene``'s model: the saved
    state must have the structure, shapes and dtypes of that model's load path state.

    Raises:
        FileNotFoundError: ``out_dir`` has no checkpoint.
        ValueError: the checkpoint is not one of this model's structure (naming the first mismatch).
    """
    path = os.path.join(out_dir, FILE)
    if not os.path.isfile(path):
        raise FileNotFoundError(f"{out_dir} has no {FILE} (a run directory written by this version of "
                                f"jaxfric run)")
    with np.load(path, allow_pickle=False) as f:
        data = {k: f[k] for k in f.files}
    meta = json.loads(str(data["meta"]))
    like = eqx.filter_eval_shape(lambda m: begin(m, control=scene.control, observe=scene.observe)[0], scene.model)
    leaves, treedef = jax.tree_util.tree_flatten(like)
    saved = [data.get(f"state/{k}") for k in range(len(leaves))]
    extra = sum(1 for k in data if k.startswith("state/")) - len(leaves)
    for k, (a, b) in enumerate(zip(saved, leaves)):
        if a is None or a.shape != tuple(b.shape) or a.dtype != np.dtype(b.dtype):
            got = "missing" if a is None else f"{a.dtype}{list(a.shape)}"
            raise ValueError(f"checkpoint in {out_dir} does not fit this model: state leaf {k} is {got}, "
                             f"expected {np.dtype(b.dtype)}{list(b.shape)}")
    if extra:
        raise ValueError(f"checkpoint in {out_dir} does not fit this model: {extra} state leaves too many")
    part = {k[len("rows/"):]: v for k, v in data.items() if k.startswith("rows/")}
    part["observed"] = {k[len("observed/"):]: v for k, v in data.items() if k.startswith("observed/")}
    snapshots: dict = {}
    for key, value in data.items():
        if key.startswith("snapshot/"):
            _, row, name = key.split("/", 2)
            snapshots.setdefault(int(row), {})[name] = value
    record = Record(parts=[part], snapshots=snapshots, wall_s=float(meta["wall_s"]), cpu_s=float(meta["cpu_s"]),
                    band_widened=[(float(t), band) for t, band in meta.get("band_widened", [])])
    return Checkpoint(path=jax.tree_util.tree_unflatten(treedef, saved), record=record), meta["config"]


class Every:
    """An ``on_chunk`` of :func:`jaxfric.loadpath.run.run` that passes the partial result to ``write`` when
    due: after the first chunk that ends ``first_s`` seconds or more after it was made, then every
    ``every_s`` seconds at least, and longer where a write takes more than 1 % of that interval, so that the
    writes take at most about 1 % of the run."""

    def __init__(self, write, every_s: float, first_s: float = 0.0):
        self.write, self.every_s = write, every_s
        self.due = time.perf_counter() + first_s

    def __call__(self, partial) -> None:
        start = time.perf_counter()
        if start < self.due:
            return
        self.write(partial())
        cost = time.perf_counter() - start
        self.due = time.perf_counter() + max(self.every_s, 100.0 * cost)


def configuration_difference(saved: dict, now: dict) -> str | None:
    """The first field in which ``now`` differs from ``saved`` (``"name: saved -> now"``), or None."""
    for key in sorted(set(saved) | set(now)):
        a, b = saved.get(key), now.get(key)
        if isinstance(a, dict) and isinstance(b, dict):
            inner = configuration_difference(a, b)
            if inner is not None:
                return f"{key}.{inner}"
        elif a != b:
            return f"{key}: {a!r} in the checkpoint, {b!r} now"
    return None
