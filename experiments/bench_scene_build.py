"""What building a scene costs in a new process: ``JAXFRIC_CACHE_DIR=off python experiments/bench_scene_build.py``.

Builds, one after the other in this process, the Nine at its spec mesh, the Nine at 100 x 2, the bead,
the blankholder and the flat die (``jaxfric.scenes.make``, spec parameters) and times each: what a test,
a notebook or a command line pays before its first step. A scene's build runs no JAX operation one by one
for its mesh (NumPy for numbers), and its tools' placement check compiles once per tool structure
(``jaxfric.loadpath.model``: a circle, a chain of faces), so a second mesh or another scene with the same
kinds of tool costs milliseconds. With ``JAXFRIC_CACHE_DIR=off`` nothing comes from an earlier process.
Writes ``experiments/results/bench_scene_build.csv`` (the import of jaxfric included in the first row).
"""

from __future__ import annotations

import os
import time

START = time.perf_counter()

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

from benchutil import write_rows  # noqa: E402
from jaxfric.scenes import make  # noqa: E402

CASES = (("nine", "mu017", {}), ("nine", "mu017", {"mesh": "100x2"}), ("bead", "th090_mu017", {}),
         ("blankholder", "shape1", {}), ("flat_die", "const_force", {}))


def main() -> None:
    rows = [{"case": "import jax and jaxfric", "seconds": f"{time.perf_counter() - START:.3f}"}]
    for scene, variant, overrides in CASES:
        t = time.perf_counter()
        make(scene, variant, overrides=overrides)
        mesh = overrides.get("mesh", "spec mesh")
        rows.append({"case": f"{scene} {variant}, {mesh}", "seconds": f"{time.perf_counter() - t:.3f}"})
        print(rows[-1]["case"], rows[-1]["seconds"], flush=True)
    rows.append({"case": "total", "seconds": f"{time.perf_counter() - START:.3f}"})
    print("total", rows[-1]["seconds"])
    write_rows(os.path.join(os.path.dirname(os.path.abspath(__file__)), "results", "bench_scene_build.csv"), rows)


if __name__ == "__main__":
    main()
