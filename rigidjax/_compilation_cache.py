"""Compiled programs kept on disk between processes: JAX's persistent compilation cache, with the
settings that keep every one of rigidjax's programs.

A first call compiles: ``simulate`` a few seconds per configuration, a closed form's motion 3-5 s,
a fit 5-30 s, the heavy top's closed form under ``jax.grad`` 20-45 s. In a new process JAX
compiles them all again unless its persistent cache is on; JAX's own default then still skips
programs that compiled in under a second, which around a simulation add up to seconds more.
"""

import os

import jax
from jax.experimental.compilation_cache import compilation_cache

DISABLE_VARIABLE = "RIGIDJAX_NO_COMPILATION_CACHE"
"""Set (to anything but an empty string) to turn the cache off: :func:`use_compilation_cache` then
changes nothing and returns None (the ``rigidjax`` command reads it too)."""


def default_cache_dir() -> str:
    """``$XDG_CACHE_HOME/rigidjax/jax``, or ``~/.cache/rigidjax/jax``."""
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return os.path.join(base, "rigidjax", "jax")


def use_compilation_cache(path: str | os.PathLike | None = None) -> str | None:
    """Keeps every compiled program on disk, so that a later process with the same calls (the same
    shapes, dtypes and options) loads its programs instead of compiling them.

    It turns on JAX's persistent compilation cache in `path` and asks it to keep every program,
    however quickly it compiled or small it is (JAX's defaults skip programs under a second of
    compile, most of those around a simulation). Call it after the imports; programs compiled
    before the call are not written. A later call with another `path` moves the cache there. The
    cache is keyed on the program, the jax and jaxlib versions
    and the XLA flags, so a changed program or a new JAX version simply compiles again; deleting
    the directory is safe. The ``rigidjax`` command does this on every run.

    Measured by ``benchmarks/first_calls.py`` (2-core CPU, float64, a new process each time), the
    first call without the cache against one with a cache an earlier process filled:
    :func:`rigidjax.torque_free_motion` of 5 bodies 2.3 -> 0.6 s; :func:`rigidjax.simulate` of
    1000 heavy tops at 200 sample times, ``"balanced"`` 3.0 -> 1.0 s, ``"exact"`` 5.8 -> 1.2 s;
    :func:`rigidjax.fit_inertia` of 240 samples 5.6 -> 1.4 s. What remains is tracing the
    functions, loading the programs and the run itself.

    **Arguments:**

    - `path`: the cache directory (created if missing). None: a directory JAX already uses
      (``JAX_COMPILATION_CACHE_DIR`` or ``jax.config``), else ``$XDG_CACHE_HOME/rigidjax/jax``
      (``~/.cache/rigidjax/jax``).

    **Returns:** the directory in use, or None when the environment variable
    ``RIGIDJAX_NO_COMPILATION_CACHE`` is set (then nothing changes).

    **Raises:**

    - `TypeError`: `path` is not a string or path.
    - `ValueError`: `path` cannot be a directory (a file is there, or it cannot be created).
    """
    if path is not None and not isinstance(path, str | os.PathLike):
        raise TypeError(
            f"use_compilation_cache: path must be a directory path (str or os.PathLike) or None, "
            f"got {type(path).__name__}"
        )
    if os.environ.get(DISABLE_VARIABLE):
        return None
    if path is None:
        path = jax.config.jax_compilation_cache_dir or os.environ.get("JAX_COMPILATION_CACHE_DIR")
    path = os.path.abspath(os.fspath(path if path else default_cache_dir()))
    try:
        os.makedirs(path, exist_ok=True)
    except OSError as error:
        raise ValueError(
            f"use_compilation_cache: path {path!r} cannot be used as the cache directory: "
            f"{error.strerror or error}"
        ) from None
    if jax.config.jax_compilation_cache_dir not in (None, path):
        # JAX opens its cache at the first compile and keeps that directory: a new one takes a
        # reset, after which the next compile opens it.
        compilation_cache.reset_cache()
    jax.config.update("jax_compilation_cache_dir", path)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", -1)
    return path
