"""Every CPU core for :func:`rigidjax.simulate`: JAX's CPU presented as one device per core.

On a CPU, JAX is one device by default, and one compiled call of ``simulate``'s chunks (a sequence
of while loops, each too small for XLA to spread over threads) runs on one core; ``simulate`` then
runs its chunks in one block per core, each from its own Python thread (:mod:`.progress`). With
several devices, ``simulate`` spreads whole chunks over them (``jax.shard_map``) in one call, each
device runs on its own core, and the results are those of one device to roundoff (the sharded
program is compiled apart: bit for bit where XLA compiles both alike). JAX fixes its devices at its
first computation, so this is a choice made once per process, before any array is created.
"""

import os
import re

import jax

from .._checks import check_positive_int

_FORCED_COUNT = re.compile(r"--xla_force_host_platform_device_count=(\d+)")


def available_cores() -> int:
    """The cores this process may run on (its CPU affinity where the system reports one)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - macOS, Windows
        return os.cpu_count() or 1


def _chosen_count() -> int | None:
    """The CPU device count the process already asked for (jax's ``jax_num_cpu_devices`` or
    ``XLA_FLAGS=--xla_force_host_platform_device_count``), or None."""
    configured = jax.config.jax_num_cpu_devices
    if configured is not None and configured > 0:
        return int(configured)
    forced = _FORCED_COUNT.findall(os.environ.get("XLA_FLAGS", ""))
    return int(forced[-1]) if forced else None


MAX_CPU_DEVICES = 4096
"""The most CPU devices :func:`use_cpu_cores` asks JAX for (4096 start in ~4 s and 0.6 GB)."""


def use_cpu_cores(count: int | None = None) -> int:
    """Presents the CPU to JAX as ``count`` devices, so that :func:`rigidjax.simulate` integrates
    its chunks on that many cores at once.

    Call it right after ``import rigidjax``, before anything computes with JAX: JAX fixes its
    devices at its first computation. Afterwards it only confirms a count already in place.

    On one device ``simulate`` already runs its chunks from one Python thread per core, outside
    ``jax.jit`` (``benchmarks/threaded_calls.py``: 1.65-1.77x on 2 cores); several devices spread the
    chunks in one compiled program, so also inside the user's ``jax.jit``. Measured with
    ``benchmarks/work_precision.py`` (10^4 tennis-racket bodies, "balanced", float64, 2-core CPU),
    before the threads: 2 devices ran 1.3-1.8x faster than one when the second core was free.
    When other programs keep every core busy, more devices can be slower (0.64-1.32x on a loaded
    2-core machine); a batch of a single chunk runs on one device whatever the count. Arrays are
    placed on the first device unless sharded, so code that does not shard runs there as before
    (a ``jax.vmap`` of a diffrax solve of 10^4 bodies measured 2-17 % slower beside a second
    device), and ``jax.devices()`` and ``jax.device_count()`` report the new count for the whole
    process.

    **Arguments:**

    - `count`: the number of CPU devices. None: the count already asked for in this process
      (``jax_num_cpu_devices``, or ``--xla_force_host_platform_device_count`` in ``XLA_FLAGS``)
      if any, else the cores the process may use.

    **Returns:** the number of CPU devices JAX now has (or will have at its first computation).

    **Raises:**

    - `ValueError`: `count` is not a positive integer, or above 4096.
    - `RuntimeError`: JAX has already computed in this process with another number of CPU devices.
    """
    count = check_positive_int(count, "count", "use_cpu_cores")
    if count is not None and count > MAX_CPU_DEVICES:
        raise ValueError(
            f"use_cpu_cores: count must be at most {MAX_CPU_DEVICES} (devices, each with its own "
            f"runtime state; more than any CPU has cores), got {count}."
        )
    wanted = count if count is not None else (_chosen_count() or available_cores())
    asked = f"use_cpu_cores({count})" if count is not None else f"use_cpu_cores() ({wanted} devices)"
    try:
        jax.config.update("jax_num_cpu_devices", wanted)
    except RuntimeError:  # JAX has started: its devices are fixed
        current = len(jax.devices("cpu"))
        if current == wanted:
            return current
        raise RuntimeError(
            f"{asked}: JAX has already started in this process with {current} CPU "
            "device(s), and its devices cannot change afterwards. Call rigidjax.use_cpu_cores() "
            "right after the imports, before any array is created or computed."
        ) from None
    return wanted
