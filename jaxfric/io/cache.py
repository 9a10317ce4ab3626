"""JAX's persistent compilation cache for jaxfric's command lines and scripts.

XLA compiles a run's program in 10 to 60 s. JAX can keep compiled programs on disk, keyed on the
program, its compile options and the jax and jaxlib versions, and read them back in a later process
instead of compiling again: a second run of the same scene, algorithm and mesh compiles nothing (JAX
still traces the program, which the key needs). The run's program can be kept because it holds no host
callback (the chunked driver, :mod:`jaxfric.loadpath.run`). Measure it with two runs in new processes,
e.g. ``jaxfric run nine --variant mu017`` twice: ``compile`` in the printed line and ``compile_s`` in
``summary.json``.

Where (:func:`cache_dir`): ``JAX_COMPILATION_CACHE_DIR`` when set (JAX's own setting, used as it is);
else ``JAXFRIC_CACHE_DIR``, where ``off`` (or an empty value) disables the cache; else
``$XDG_CACHE_HOME/jaxfric/xla`` (``~/.cache/jaxfric/xla``).

What: every compiled program, however short its compilation (:data:`MIN_COMPILE_SECONDS`, JAX's
``jax_persistent_cache_min_compile_time_secs``, whose default of one second keeps only the run's
programs; ``JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS`` in the environment still chooses). Building a
scene runs array code outside any compiled function, which JAX compiles primitive by primitive, and checks
each tool's placement with a compiled projection: for the Nine 54 programs, 3 to 4 s of compilation in
every process, each under a second. Kept, a second build of the same scene in a new process takes 1.0 s
instead of 3.4 s (``python experiments/bench_compile.py --scene-build``), for 54 files and 0.3 MB in the
folder. A run's program takes 0.1 to 1 MB on the CPU. The folder is not trimmed (JAX's size limit,
``jax_compilation_cache_max_size``, needs the ``filelock`` package, not a dependency of jaxfric): remove it
to reclaim the space.
"""

from __future__ import annotations

import os

__all__ = ["cache_dir", "enable_compilation_cache", "MIN_COMPILE_SECONDS"]

MIN_COMPILE_SECONDS = 0.0   # keep every program (see the module's docstring)


def cache_dir(environ=None) -> str | None:
    """The cache folder the environment asks for (see the module's docstring), or None for no cache."""
    env = os.environ if environ is None else environ
    if env.get("JAX_COMPILATION_CACHE_DIR"):
        return env["JAX_COMPILATION_CACHE_DIR"]
    if "JAXFRIC_CACHE_DIR" in env:
        chosen = env["JAXFRIC_CACHE_DIR"].strip()
        return None if chosen in ("", "off") else chosen
    base = env.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return os.path.join(base, "jaxfric", "xla")


def enable_compilation_cache(path: str | None = None) -> str | None:
    """Turn JAX's persistent compilation cache on in this process, in ``path`` or :func:`cache_dir`; call it
    before the first compilation. Returns the folder, or None when the cache is off or its folder cannot
    be made (the run then compiles as without it)."""
    import jax

    current = getattr(jax.config, "jax_compilation_cache_dir")  # noqa: B009 - not in JAX's type stubs
    if not current:  # else set by JAX_COMPILATION_CACHE_DIR or by an earlier call
        path = path or cache_dir()
        if path is None:
            return None
        try:
            os.makedirs(path, exist_ok=True)
        except OSError:
            return None
        jax.config.update("jax_compilation_cache_dir", path)
        current = path
    if "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS" not in os.environ:
        jax.config.update("jax_persistent_cache_min_compile_time_secs", MIN_COMPILE_SECONDS)
    return current
