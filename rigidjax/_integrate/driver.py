"""The one place rigidjax steps through time.

Every integration in the package ends here: :func:`rigidjax.simulate` (each chunk of bodies, with
any diffrax solver or rigidjax's structure-preserving ones), the known-torque windows of
:func:`rigidjax.fit_inertia`, and whatever comes next. The driver knows nothing of rigid bodies: it
takes a vector field, a solver, a step-size rule and sample times, and returns the states at those
times with a result code. Callers own the state layout, the checks and the batching.
"""

import contextlib
import threading
from collections.abc import Callable
from typing import Any, NamedTuple

import diffrax
import equinox._errors as _equinox_errors
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, Int, PyTree


class Solution(NamedTuple):
    """States at the sample times and how the solve went."""

    ys: PyTree
    """The state at each sample time: every leaf gains a leading time axis ``(T, ...)``."""
    result: Int[Array, ""]
    """diffrax's result code: ``SUCCESSFUL``, ``MAX_STEPS_REACHED``, ``EVENT_OCCURRED``, ..."""
    num_steps: Int[Array, ""]
    """Steps taken, accepted and rejected."""


SUCCESSFUL = int(diffrax.RESULTS.successful._value)
MAX_STEPS_REACHED = int(diffrax.RESULTS.max_steps_reached._value)
EVENT_OCCURRED = int(diffrax.RESULTS.event_occurred._value)
DT_MIN_REACHED = int(diffrax.RESULTS.dt_min_reached._value)


MAX_FIXED_STEPS = 2**30
"""The most steps a fixed-step run takes (its grid of step times: 8 GiB in float64)."""


def fixed_step_grid(ts, dt: float):
    """Step times for a fixed-step solver that land on every sample time: each interval
    ``[ts[i], ts[i+1]]`` is cut into ``ceil((ts[i+1] - ts[i]) / dt)`` equal steps.

    ``ts`` must be concrete (a NumPy array): the grid fixes the number of steps. Returns the grid
    (float64 NumPy) and the number of steps.
    """
    import numpy as np

    ts = np.asarray(ts, dtype=np.float64)
    if ts.shape[0] < 2:
        return ts, 0
    gaps = np.diff(ts)
    with np.errstate(over="ignore"):  # a subnormal dt: infinitely many steps, refused below
        counts = np.maximum(1.0, np.ceil(gaps / dt * (1 - 1e-12)))
    total = float(np.sum(counts))  # counted in floats first: a tiny dt overflowed int64
    if not total <= MAX_FIXED_STEPS:
        raise ValueError(
            f"dt0 = {dt:g} takes {total:.3g} fixed steps over ts ({ts[-1] - ts[0]:g} s), more than "
            f"{MAX_FIXED_STEPS:,}, whose step times alone would fill {8 * total / 2**30:.3g} GiB: take a "
            "larger dt0, or an adaptive step-size controller, whose steps follow the motion."
        )
    counts = counts.astype(np.int64)
    pieces = [ts[:1]]
    for start, gap, count in zip(ts[:-1], gaps, counts, strict=True):
        inner = start + gap * np.arange(1, count, dtype=np.float64) / count
        pieces.extend([inner, [start + gap]])
    grid = np.concatenate(pieces)
    grid[np.cumsum(np.concatenate([[0], counts]))] = ts  # sample times exactly, not start + gap
    return grid, int(counts.sum())


try:  # forward-mode tracers; matched by class name where JAX moves the class
    from jax.interpreters.ad import JVPTracer as _JVP_TRACER
except ImportError:  # pragma: no cover
    _JVP_TRACER = None


def _tracer_kinds(x) -> set[str]:
    """The class names of the tracers ``x`` is made of, at every depth of nesting (``JVPTracer``
    for one of forward mode): under ``jacfwd(vmap(f))`` a forward-mode tracer is wrapped in a
    batching tracer, under ``jit(jacfwd(f))`` it wraps a jit tracer. Two levels of reverse mode
    (``jacrev(jacrev(f))``) add ``"LinearizeTracer x2"``."""
    kinds, linearize = set(), 0
    for _ in range(64):  # tracers nest once per transformation
        if not isinstance(x, jax.core.Tracer):
            break
        kind = "JVPTracer" if _JVP_TRACER is not None and isinstance(x, _JVP_TRACER) else type(x).__name__
        kinds.add(kind)
        linearize += kind == "LinearizeTracer"
        inner = [getattr(x, name, None) for name in ("primal", "val")]
        x = next((v for v in inner if isinstance(v, jax.core.Tracer)), None)
    if linearize > 1:
        kinds.add("LinearizeTracer x2")
    return kinds


def _traced_by(x, names: tuple[str, ...]) -> bool:
    """Whether ``x`` is, at any depth of nesting, a tracer whose class is named in ``names``."""
    return not _tracer_kinds(x).isdisjoint(names)


def is_differentiated(*inputs) -> bool:
    """Whether any array among ``inputs`` (pytrees) is being differentiated, in either mode, when
    the call is traced. A tracer closed over by a function among them is not seen."""
    leaves = jax.tree_util.tree_leaves(inputs)
    return any(_traced_by(x, ("JVPTracer", "LinearizeTracer")) for x in leaves)


def default_adjoint(*inputs) -> diffrax.AbstractAdjoint:
    """The adjoint when the caller names none: ``diffrax.ForwardMode()`` when any array among
    ``inputs`` (pytrees) carries forward-mode tangents, ``diffrax.DirectAdjoint()`` when they carry
    both forward-mode tangents and reverse mode's linearize tracers (a second derivative such as
    ``jax.hessian``) or reverse mode's alone on several devices, else
    ``diffrax.RecursiveCheckpointAdjoint()``.

    The checkpointed adjoint is a ``custom_vjp``, which JAX cannot push tangents through;
    ``ForwardMode`` is a plain loop, which JAX cannot transpose; the direct adjoint's bounded loop
    allows both, at a cost in time and memory that grows with ``max_steps``. Each mode gets the
    cheapest one that works.
    """
    leaves = jax.tree_util.tree_leaves(inputs)
    kinds = set().union(*(_tracer_kinds(x) for x in leaves))
    if ("JVPTracer" in kinds and "LinearizeTracer" in kinds) or "LinearizeTracer x2" in kinds:
        # Both modes nested (jax.hessian, jacrev of jacfwd), or reverse mode twice (jacrev of
        # jacrev: the checkpointed adjoint's loop cannot be differentiated in reverse again): only
        # the direct adjoint does both.
        return diffrax.DirectAdjoint()
    if "JVPTracer" in kinds:
        return diffrax.ForwardMode()
    if "LinearizeTracer" in kinds and jax.device_count() > 1:
        # Reverse mode through chunks spread over several devices (shard_map): the checkpointed
        # adjoint's backward loop failed there ("Closure-converted function called with different
        # dynamic arguments"); the direct adjoint transposes.
        return diffrax.DirectAdjoint()
    return diffrax.RecursiveCheckpointAdjoint()


def _is_custom_vjp_jvp_error(err: Exception) -> bool:
    return isinstance(err, TypeError) and "forward-mode autodiff (jvp) to a custom_vjp" in str(err)


def solve_in_either_mode(call: Callable[[diffrax.AbstractAdjoint], Any], adjoint, chosen: bool):
    """``call(adjoint)``; when the adjoint was ``chosen`` by :func:`default_adjoint` (not the user's)
    and tangents reached the solve by a way the inputs do not show (a tracer closed over by a torque
    function), JAX refuses to push them through the checkpointed adjoint while tracing: the call is
    made again with ``diffrax.ForwardMode()``."""
    try:
        return call(adjoint)
    except TypeError as err:
        if not (chosen and _is_custom_vjp_jvp_error(err)):
            raise
    return call(diffrax.ForwardMode())


@contextlib.contextmanager
def _without_diffrax_runtime_checks(switch_off: bool):
    """diffrax checks ``ts`` and ``dt0`` at run time with equinox errors, which are host callbacks;
    JAX keeps no program with a host callback in its persistent compilation cache, so every process
    would compile every integration again. rigidjax's callers have checked both already (times
    finite and increasing, ``dt0`` positive), so the checks are switched off while the solve is
    traced. A solve asked to raise on failure (``throw=True``) keeps them all. Equinox reads its
    default mode per call; if that global moves, the checks simply stay. Solves traced at the same
    time in several threads share the switch: the first one in turns it off, the last one out
    restores it."""
    global _switched_off
    if not switch_off:
        yield
        return
    with _switch_lock:
        if _switched_off == 0:
            if getattr(_equinox_errors, "EQX_ON_ERROR", None) != "raise":
                switch_off = False
            else:
                _equinox_errors.EQX_ON_ERROR = "off"
        elif getattr(_equinox_errors, "EQX_ON_ERROR", None) != "off":
            switch_off = False  # the global moved meanwhile: leave it
        if switch_off:
            _switched_off += 1
    if not switch_off:
        yield
        return
    try:
        yield
    finally:
        with _switch_lock:
            _switched_off -= 1
            if _switched_off == 0:
                _equinox_errors.EQX_ON_ERROR = "raise"


_switch_lock = threading.Lock()
_switched_off = 0


def solve(
    vector_field: Callable[[Any, PyTree, Any], PyTree],
    solver: diffrax.AbstractSolver,
    y0: PyTree,
    ts: Float[Array, " T"],
    *,
    stepsize_controller: diffrax.AbstractStepSizeController,
    dt0: Any = None,
    t0: Any = None,
    args: Any = None,
    adjoint: diffrax.AbstractAdjoint | None = None,
    max_steps: int = 100_000,
    event: diffrax.Event | None = None,
    throw: bool = False,
    save_fn: Callable | None = None,
) -> Solution:
    """Integrates ``dy/dt = vector_field(t, y, args)`` from ``y0`` and samples it at ``ts``.

    **Arguments:**

    - `vector_field`: ``f(t, y, args)``, any pytree state.
    - `solver`: any diffrax solver, including rigidjax's structure-preserving ones.
    - `y0`: the state at ``t0``.
    - `ts`: increasing sample times ``(T,)``; the solve ends at ``ts[-1]``.
    - `stepsize_controller`: the step-size rule (``PIDController``, ``ConstantStepSize``,
      ``StepTo`` for a fixed grid).
    - `dt0`: the first step (None: the controller's choice).
    - `t0`: the start time; ``ts[0]`` when None.
    - `args`: passed to ``vector_field``.
    - `adjoint`: how to differentiate; reverse-mode checkpointing when None.
    - `max_steps`: the step limit; reaching it is the result ``MAX_STEPS_REACHED``.
    - `event`: a diffrax ``Event`` that stops the solve (result ``EVENT_OCCURRED``).
    - `throw`: raise on failure instead of returning the result code.
    - `save_fn`: ``save_fn(t, y, args)``, what is kept of the state at each sample time (None: the
      state itself), as diffrax's ``SaveAt(fn=...)``.

    **Returns:** a :class:`Solution` with the states at ``ts``.
    """
    # Only the two ends: saved as such, not through the dense output, which would make every step
    # keep its stages for an interpolation never asked for (a quarter of "balanced"'s time).
    ends_only = t0 is None and ts.shape[0] == 2
    fn = {} if save_fn is None else {"fn": save_fn}
    saveat = diffrax.SaveAt(t0=True, t1=True, **fn) if ends_only else diffrax.SaveAt(ts=ts, **fn)
    with _without_diffrax_runtime_checks(switch_off=not throw):
        solution = diffrax.diffeqsolve(
            diffrax.ODETerm(vector_field),
            solver,
            ts[0] if t0 is None else t0,
            ts[-1],
            dt0,
            y0,
            args=args,
            saveat=saveat,
            stepsize_controller=stepsize_controller,
            adjoint=diffrax.RecursiveCheckpointAdjoint() if adjoint is None else adjoint,
            max_steps=max_steps,
            throw=throw,
            event=event,
        )
    result = jnp.asarray(solution.result._value)
    ys = solution.ys
    if ends_only:
        # SaveAt(t1) keeps the state where a failed solve stopped; the end was not reached: inf, as
        # SaveAt(ts) leaves a sample it did not reach.
        reached = result == SUCCESSFUL
        ys = jax.tree_util.tree_map(lambda y: y.at[-1].set(jnp.where(reached, y[-1], jnp.inf)), ys)
    return Solution(ys, result, solution.stats["num_steps"])
