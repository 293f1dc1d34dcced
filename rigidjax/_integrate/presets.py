"""The ``accuracy`` presets of :func:`rigidjax.simulate`: a diffrax solver and a relative tolerance.

Chosen by measurement (``benchmarks/batch_strategies.py``, 10^4 tennis-racket bodies, shared step,
max norm): Dopri8 is faster at every error below ~1e-5; at rtol 1e-8 it needs 128 shared steps where
Tsit5 needs 527. Large batches run it with its stages written out
(:class:`.solvers.unrolled.UnrolledDopri8`, the same values at about a third of the cost per step;
see :func:`preset_solver`).
"""

from types import MappingProxyType
from typing import Any

import diffrax
import jax
import jax.numpy as jnp
import numpy as np

from .._checks import check_flag, check_positive_int, known_values
from .solvers.unrolled import UnrolledDopri8

PRESETS = MappingProxyType(
    {
        "fast": (diffrax.Tsit5, 1e-5),
        "balanced": (UnrolledDopri8, 1e-8),
        "precise": (UnrolledDopri8, 1e-11),
    }
)
"""``accuracy`` name -> ``(diffrax solver class, rtol)``; read-only. ``"exact"`` is the closed form.
What ``simulate`` runs for a given batch and dtype is :func:`preset`'s answer."""

ACCURACIES = (*PRESETS, "exact")


UNROLLED_MIN_BODIES = 1024
"""The smallest batch the presets run with :class:`UnrolledDopri8`; smaller ones run diffrax's own
Dopri8 (see :func:`preset_solver`)."""


def preset_solver(accuracy: str, differentiated: bool, n_bodies: int) -> diffrax.AbstractSolver:
    """The preset's solver. :class:`UnrolledDopri8` costs about a third of diffrax's Dopri8 per body
    and step (``benchmarks/results/step_cost.md``: 229 against 661 ns in ``simulate``) but takes
    longer to compile (a free body with 11 samples: a first call 3.7-3.9 s against
    2.5-2.6 s, a first ``jax.grad`` 19-20 s against 7-8 s), so it runs where the steps outweigh the
    compile: batches of at least ``UNROLLED_MIN_BODIES`` bodies, not differentiated. Elsewhere
    diffrax's Dopri8 runs; the two agree to rounding."""
    solver = PRESETS[accuracy][0]
    if solver is UnrolledDopri8 and (differentiated or n_bodies < UNROLLED_MIN_BODIES):
        return diffrax.Dopri8()
    return solver()


def preset_rtol(accuracy: str, dtype) -> float:
    """The preset's relative (and absolute) tolerance in ``dtype``: never below ten roundoff units
    (float32: 1.2e-6, above "balanced"'s and "precise"'s own)."""
    return max(PRESETS[accuracy][1], 10 * float(np.finfo(dtype).eps))


def preset(
    accuracy: str, n_bodies: int = 1, dtype: Any = None, differentiated: bool = False
) -> tuple[diffrax.AbstractSolver, float]:
    """The solver and tolerance ``rigidjax.simulate(..., accuracy=accuracy)`` integrates with.

    :data:`PRESETS` names each preset's solver class and tolerance; the run differs from it in
    two ways. The unrolled Dopri8 runs batches of at least 1024 bodies that are not
    differentiated (it compiles for longer: below that diffrax's own Dopri8, the same values to
    rounding); and no tolerance is below ten roundoff units of the dtype (float32: 1.2e-6, above
    ``"balanced"``'s 1e-8 and ``"precise"``'s 1e-11).

    **Arguments:**

    - `accuracy`: ``"fast"``, ``"balanced"`` or ``"precise"`` (``"exact"`` integrates nothing).
    - `n_bodies`: the number of bodies in the batch (all of its leading axes together).
    - `dtype`: float32 or float64; default JAX's default float.
    - `differentiated`: whether ``simulate`` runs under ``jax.grad``, ``jacfwd`` or ``jvp``.

    **Returns:** ``(solver, rtol)``: a diffrax solver instance, and the relative tolerance (the
    absolute one is the same, on omega scaled by each body's speed).
    """
    if accuracy not in PRESETS:
        hint = " (the closed form: no solver)" if accuracy == "exact" else ""
        raise ValueError(
            f"preset: accuracy must be one of {', '.join(map(repr, PRESETS))}{hint}; got {accuracy!r}."
        )
    n_bodies = check_positive_int(n_bodies, "n_bodies", "preset")
    dtype = jnp.dtype(jnp.result_type(float) if dtype is None else dtype)
    if dtype not in (np.float32, np.float64):
        raise ValueError(f"preset: dtype must be float32 or float64, got {dtype}.")
    differentiated = check_flag(differentiated, "differentiated", "preset")
    return preset_solver(accuracy, differentiated, n_bodies), preset_rtol(accuracy, dtype)


BODIES_PER_ACCELERATOR_CORE = 512
"""Default chunk on an accelerator, per streaming multiprocessor (67584 bodies on an H200's 132)."""

CHUNK_MEMORY_SHARE = 8
"""On an accelerator, a chunk's samples and solver stages take at most this share of the device's
memory (``1 / CHUNK_MEMORY_SHARE``)."""


def default_chunk_size(n_samples: int = 2, itemsize: int = 8) -> int:
    """Bodies per shared-step chunk when the caller names none.

    On CPU 256, where a chunk's stages stay in the core's cache (``benchmarks/step_cost.py``, 10^4
    tennis-racket bodies, "balanced": 229 ns per body and step in chunks of 256 against 318 in
    chunks of 1024).

    On an accelerator, ``BODIES_PER_ACCELERATOR_CORE`` per core (streaming multiprocessor), about
    the batch from which a step's time grows with the number of bodies; beyond it, a larger chunk's
    shared step (set by its most demanding body) costs more than running chunks one after another.
    Measured on an H200 (132 multiprocessors), tennis-racket bodies, "balanced": one chunk of 10^4
    bodies 0.020 s, of 10^5 0.059 s; 10^6 bodies in chunks of 65536 0.44 s (0.028 s a chunk), of
    262144 0.60 s (0.15 s a chunk), in one 0.59 s (``benchmarks/results/accelerator.gpu.json``).
    Capped so that a chunk's ``n_samples`` samples and its solver's stages (about 32 states) take
    at most ``1 / CHUNK_MEMORY_SHARE`` of the device's memory."""
    device = jax.devices()[0]
    if device.platform == "cpu":
        return 256
    cores = getattr(device, "core_count", None)
    chunk = BODIES_PER_ACCELERATOR_CORE * cores if cores else 65536
    limit = (device.memory_stats() or {}).get("bytes_limit")
    if limit:
        per_body = (n_samples + 32) * 7 * 2 * itemsize  # the samples twice: saved, then gathered
        chunk = min(chunk, max(1, limit // (CHUNK_MEMORY_SHARE * per_body)))
    return int(chunk)


MIN_MAX_STEPS = 100_000
"""The smallest default step limit per chunk, and the limit when the inputs' values are unknown."""

MAX_STEPS_LIMIT = 2**31 - 1
"""The largest ``max_steps``: the largest 32-bit integer (a run of that many steps takes hours)."""

LARGEST_DEFAULT_MAX_STEPS = 2**30
"""The largest default step limit: a span that needs more raises rather than runs for hours."""

STEPS_PER_TURN = 100
"""Default step budget per turn of the fastest body: ``"precise"`` (Dopri8, rtol 1e-11) took 22 steps
per turn of a body spinning at 2000 rad/s, so this leaves about 4x headroom (also for the error
estimate's tighter second solve)."""


def _spread_over_processes(x) -> bool:
    """An array of a batch sharded over several processes: its values cannot be fetched here."""
    return isinstance(x, jax.Array) and not x.is_fully_addressable


_largest_norm_on_devices = jax.jit(lambda w: jnp.max(jnp.linalg.norm(w, axis=-1)))
_span_on_devices = jax.jit(lambda t: t[-1] - t[0])


def _largest_norm(omega0) -> float:
    if _spread_over_processes(omega0):  # reduced on the devices: every process gets the same value
        return float(_largest_norm_on_devices(omega0))
    omega0 = np.asarray(omega0, np.float64)
    # Scaled by the largest component first: the square of one above ~1e154 overflows (a
    # RuntimeWarning from NumPy, and an infinite speed where the span check should name it).
    largest = np.max(np.abs(omega0))
    if not np.isfinite(largest) or largest == 0:
        return float(largest)
    return float(largest * np.max(np.linalg.norm(omega0 / largest, axis=-1)))


def _span(ts) -> float:
    if _spread_over_processes(ts):
        return float(_span_on_devices(ts))
    ts = np.asarray(ts, np.float64)
    return float(ts[-1] - ts[0])


def default_max_steps(omega0, ts) -> int:
    """The step limit per chunk when the caller names none: ``STEPS_PER_TURN`` steps per turn of the
    fastest body over the span of ``ts`` (``max|omega0| (ts[-1] - ts[0]) / 2 pi`` turns) plus one per
    sample interval (``"precise"`` ends a step on every sample time); ``MIN_MAX_STEPS`` when that is
    less, else rounded up to a power of two (the limit is compiled into the program: few distinct
    values, few compilations); a span that needs more than ``LARGEST_DEFAULT_MAX_STEPS`` is a
    ``ValueError``. Inside ``jit`` the values are unknown: ``MIN_MAX_STEPS``.

    The limit only bounds the solver's loop: it costs no memory or time when forward, and the
    checkpointed reverse mode keeps ``log(max_steps)`` checkpoints."""
    values = known_values((omega0, ts))
    if values is None:
        return MIN_MAX_STEPS
    omega0, ts = values
    if omega0.size == 0 or ts.shape[0] < 2:
        return MIN_MAX_STEPS
    fastest, span = _largest_norm(omega0), _span(ts)
    turns = fastest * span / (2 * np.pi)
    need = STEPS_PER_TURN * turns + (ts.shape[0] - 1)
    if not np.isfinite(need) or need <= MIN_MAX_STEPS:  # non-finite input is reported by the checks
        return MIN_MAX_STEPS
    if need > LARGEST_DEFAULT_MAX_STEPS:
        # Hours of stepping that would end at the limit anyway: say so now.
        raise ValueError(
            f"simulate: ts spans {turns:.3g} turns of the fastest body (|omega0| = {fastest:.3g} rad/s "
            f"over {span:.3g} s), more than an integrator steps through within the default limit of "
            f"{LARGEST_DEFAULT_MAX_STEPS:,} steps ({LARGEST_DEFAULT_MAX_STEPS // STEPS_PER_TURN:,} turns). "
            "A torque-free body or a Lagrange top has a closed form at any time: accuracy='exact'; "
            "otherwise shorten ts, or pass max_steps to integrate anyway (hours per chunk)."
        )
    return int(2 ** int(np.ceil(np.log2(need))))


class FaultStopPIDController(diffrax.PIDController):
    """diffrax's ``PIDController`` that also stops when a *rejected* step would shrink below
    ``fault_dtmin``.

    A body whose torque or state turns NaN makes every trial step fail; without a floor the chunk
    would burn ``max_steps`` rejections and be reported as out of steps. diffrax's own ``dtmin``
    cannot be the floor when steps land on sample times (``step_ts``): the controller grows the
    next step from the last *accepted* one, which a nearby sample time may have clipped to almost
    nothing, and a healthy body would stop. Accepted steps never trigger this floor.
    """

    fault_dtmin: Any = None

    def adapt_step_size(self, t0, t1, y0, y1_candidate, args, y_error, error_order, controller_state):
        keep, next_t0, next_t1, made_jump, state, result = super().adapt_step_size(
            t0, t1, y0, y1_candidate, args, y_error, error_order, controller_state
        )
        if self.fault_dtmin is not None:
            stuck = jnp.logical_not(keep) & (next_t1 - next_t0 < self.fault_dtmin)
            result = diffrax.RESULTS.where(stuck, diffrax.RESULTS.dt_min_reached, result)
        return keep, next_t0, next_t1, made_jump, state, result
