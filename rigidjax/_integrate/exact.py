"""``simulate(..., accuracy="exact")``: the closed forms (torque-free bodies, Lagrange's top) with
simulate's checks, evaluated at every sample time in one program (on CPU, blocks of bodies in a
loop), no integration."""

import contextlib
import functools
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.custom_derivatives import SymbolicZero

from .._checks import (
    StaticValue,
    check_model,
    check_state,
    check_times,
    check_times_shape,
    checks_done,
    collected_failures,
    error_if,
    evaluated_now,
    float_dtype,
    is_full_tensor,
    is_traced,
    known_values,
    packed_failures,
    raise_collected,
)
from .._closed_form.barrier import _materialised
from .._closed_form.heavy_top import lagrange_top_motion, lagrange_top_parts
from .._closed_form.jacobi import upper_side
from .._closed_form.torque_free import _torque_free_motion, _torque_free_omega
from .._dynamics.models import FreeBody, HeavyTop
from . import batching
from .driver import is_differentiated
from .inputs import checked_inputs
from .trajectory import Trajectory

__all__ = ["simulate_exact"]


@eqx.filter_jit
def _exact(model, omega0, q0, ts, chunk_size: int | None, values_checked: bool, one_side: bool = True):
    """The closed forms' program; ``values_checked``: the inputs' values were checked before it (no
    run-time checks, and so no host callback, in the program); ``one_side``: see
    :func:`_exact_motion`."""
    with checks_done() if values_checked else contextlib.nullcontext():
        inputs = _exact_inputs(model, omega0, q0, ts)
    return _exact_motion(*inputs, chunk_size, one_side)


@functools.partial(jax.jit, static_argnums=4)
def _collected_program(model, omega0, q0, ts, chunk_size: int | None):
    with collected_failures() as failures:
        inputs = _exact_inputs(model, omega0, q0, ts)
    # The closed forms' own checks test the same inputs: here their failures are the ones collected
    # above, raised as ValueError after the program (in the program they would raise first).
    with checks_done():
        motion = _exact_motion(*inputs, chunk_size)
    codes, messages = packed_failures(failures)
    arrays, static = eqx.partition(motion, eqx.is_array)
    return arrays, codes, StaticValue((static, messages))


def _exact_collected(model, omega0, q0, ts, chunk_size: int | None):
    """The closed forms' program for concrete inputs: the conditions of the input checks are returned
    beside the motion (for :func:`.raise_collected`), one program and no host callback. A ``jax.jit``
    of arrays, not ``eqx.filter_jit``: its dispatch cost ~0.24 ms less per call (one body: 0.38 ->
    0.14 ms)."""
    arrays, codes, static = _collected_program(model, omega0, q0, ts, chunk_size)
    motion_static, messages = static.value
    return eqx.combine(arrays, motion_static), (codes, messages)


def _exact_inputs(model, omega0, q0, ts):
    model = check_model(model, "simulate")
    omega0, q0 = check_state(omega0, q0, "simulate")
    ts = check_times(ts, "simulate")
    if isinstance(model, HeavyTop):
        model = eqx.tree_at(
            lambda top: (top.inertia, top.com), model, _lagrange_checked(model.inertia, model.com)
        )
    return model, omega0, q0, ts


def block_elements() -> int:
    """Body-samples per block of a closed form's evaluation. On CPU a block's few dozen
    ``(bodies, samples)`` intermediates then stay in the core's cache (XLA materialises them): 10^4
    bodies at 200 samples, medians of 7 alternated calls, the free body's omega and q 348 ms in one
    block against 223 ms in blocks of 655 bodies (2^17 body-samples), Lagrange's top 243 against
    200 ms; at 800 samples 1590 against 847 ms. On accelerators one block."""
    return 2**17 if jax.default_backend() == "cpu" else 2**62


def _exact_motion(model, omega0, q0, ts, chunk_size, one_side=True):
    """The closed form at ``ts``, in blocks of ``chunk_size`` bodies (None: :func:`block_elements`).

    Lagrange's tops in several blocks are sorted into blocks of one side (:func:`_one_side_blocks`)
    where ``one_side``; otherwise each block evaluates both sides' series: one program instead of
    two. ``simulate`` asks for that where it sees a derivative taken: 10^4 tops at 50 samples,
    ``jit(grad)`` of a function of the motion compiled in 24 s instead of 49 s and ran in 0.29 s
    instead of 0.49 s (``jit`` of a ``jvp``: 19 s against 49 s, 0.33 s against 0.46 s; XLA at
    -O1), as the sorting's gathers and the branches weigh more in a derivative than the saved
    series."""
    batch = batching.batch_shape(model, omega0, q0)
    n_bodies, n_times = math.prod(batch), ts.shape[0]
    heavy = isinstance(model, HeavyTop)
    per_body = {"inertia": (model.inertia, 3), "omega0": (omega0, 3)}
    if q0 is not None:
        per_body["q0"] = (q0, 4)
    if heavy:
        per_body.update(com=(model.com, 3), mass=(model.mass, 0), gravity=(model.gravity, 0))
    flat = {
        name: jnp.broadcast_to(x, batch + (k,) * bool(k)).reshape((n_bodies,) + (k,) * bool(k))
        for name, (x, k) in per_body.items()
    }
    # With two sample times (the state at one time) the first is the initial state itself and the
    # closed form is evaluated at the second only: a samples axis of one element, over which XLA
    # vectorises the bodies (it did not over a samples axis of two: 10^4 bodies' omega and q 8.4 ->
    # 4.4 ms). With more samples, writing the first one over cost up to 1.5x: all are evaluated.
    t = ts[1:] - ts[0] if n_times == 2 else ts - ts[0]

    def motion(bodies, t, side=None):
        """omega ``(bodies, samples, 3)`` and the orientation ``(bodies, samples, 4)`` (or None) at
        the times ``t`` after the first; ``side``: see :func:`.lagrange_top_at`."""
        first_omega = bodies["omega0"]
        first_q = bodies.get("q0")  # checked and normalised by _exact_inputs
        if n_times == 1:
            return first_omega[:, None], None if q0 is None else first_q[:, None]
        inertia, omega0 = bodies["inertia"][:, None], bodies["omega0"][:, None]
        if heavy:
            omega, q = lagrange_top_motion(*(bodies[name][:, None] for name in _TOP_INPUTS), t, side)
        elif q0 is None:
            omega, q = _torque_free_omega(inertia, omega0, t, checked=False), None
        else:
            omega, q = _torque_free_motion(inertia, omega0, bodies["q0"][:, None], t, checked=False)
        if n_times == 2:
            # Computed in full before the stacking (see _closed_form.barrier): 10^4 bodies' omega
            # and q 5.5 -> 4.0 ms.
            omega, q = _materialised((omega, q)) if q is not None else (_materialised((omega,))[0], None)
            omega = jnp.stack([first_omega, omega[:, 0]], axis=1)
            return omega, None if q is None else jnp.stack([first_q, q[:, 0]], axis=1)
        return omega, q

    per_block = max(1, block_elements() // max(n_times, 1)) if chunk_size is None else chunk_size
    block = min(per_block, n_bodies)
    if n_bodies <= per_block:
        omega, orientation = motion(flat, t)
    elif heavy and n_times > 1 and one_side:
        omega, orientation = _one_side_blocks(motion, flat, t, per_block)
    else:
        block = batching.plan_chunks(n_bodies, per_block, shardable=False).chunk
        omega, orientation = _plain_blocks(motion, flat, t, per_block)
    omega = omega.reshape(batch + omega.shape[1:])
    if orientation is not None:
        orientation = orientation.reshape(batch + orientation.shape[1:])
    return Trajectory(
        ts=ts,
        omega=omega,
        orientation=orientation,
        model=model,
        success=jnp.ones(batch, bool),
        stats={
            "num_steps": jnp.zeros((), jnp.int32),
            "chunk_size": block,
            # Nothing normalises the closed forms' quaternions; Trajectory.invariants measures their
            # norm from the samples when asked. Computed here, alongside the samples, it cost 15-20 %
            # of the evaluation on CPU (10^4 bodies at 2 samples 9.8 -> 8.5 ms, 655 at 200
            # 17.7 -> 14.3 ms): XLA then writes each component of q to memory a second time.
            "quaternion_norm_error": None,
        },
    )


_TOP_INPUTS = ("inertia", "mass", "com", "gravity", "omega0", "q0")
"""Lagrange's top's per-body inputs, in the order of :func:`.lagrange_top_motion`'s arguments."""


def _lagrange_parts(bodies):
    """:func:`.lagrange_top_parts` of flat per-body inputs, with a samples axis to broadcast against."""
    return lagrange_top_parts(*(bodies[name][:, None] for name in _TOP_INPUTS))


def _plain_blocks(motion, flat, t, per_block):
    """``motion`` of the bodies in blocks of ``per_block`` in a loop; the last block is filled up
    with copies of the last body."""
    plan = batching.plan_chunks(flat["omega0"].shape[0], per_block, shardable=False)
    blocks = {name: batching.to_chunks(plan, x) for name, x in flat.items()}
    outputs = jax.lax.map(lambda bodies: motion(bodies, t), blocks)
    return tuple(batching.from_chunks(plan, x) for x in outputs)


def _one_side_blocks(motion, flat, t, per_block):
    """:func:`_sorted_blocks`, whose derivatives are those of :func:`_plain_blocks`: a derivative
    taken outside a ``jit`` around ``simulate`` (which therefore cannot ask for plain blocks) gets
    the plain blocks' program too. Differentiated, the values are the plain blocks' (the same to
    roundoff). 60 random tops in blocks of 7 at 11 samples: ``jax.jvp`` of a ``jit`` around
    ``simulate`` traced in 7 s instead of 16 s and compiled in 34 s instead of 56 s (XLA at -O1)."""

    @jax.custom_jvp
    def sorted_blocks(flat, t):
        return _sorted_blocks(motion, flat, t, per_block)

    @functools.partial(sorted_blocks.defjvp, symbolic_zeros=True)
    def _(primals, tangents):
        # Inputs without a tangent enter as constants, so that the closed form's derivative takes
        # no direction for them (see .derivatives).
        leaves, tree = jax.tree.flatten(primals)
        dots = jax.tree.leaves(tangents, is_leaf=lambda x: isinstance(x, SymbolicZero))
        live = [i for i, dot in enumerate(dots) if not isinstance(dot, SymbolicZero)]

        def plain(*live_leaves):
            inputs = list(leaves)
            for i, x in zip(live, live_leaves, strict=True):
                inputs[i] = x
            return _plain_blocks(motion, *jax.tree.unflatten(tree, inputs), per_block)

        return jax.jvp(plain, [leaves[i] for i in live], [dots[i] for i in live])

    return sorted_blocks(flat, t)


def _sorted_blocks(motion, flat, t, per_block):
    """Lagrange's tops in blocks whose elliptic parameters ``m`` all lie on one side of 1/2, so that
    each block evaluates one side's theta series (:func:`.lagrange_top_at`'s ``side``) instead of both.

    The tops with ``m <= 1/2`` fill the first blocks, those above the rest; each side's last block is
    filled up with copies of its last top, so there is one block more than plain blocks would need.
    10^4 tops of ``rigidjax simulate``'s heavy-top scene with I1 = I2 (a fifth of them above 1/2),
    200 samples: see ``benchmarks/heavy_top_exact.py``."""
    n = flat["mass"].shape[0]
    parts = _lagrange_parts(flat)
    upper = upper_side(parts["m"][:, 0])
    order = jnp.argsort(upper.astype(jnp.int8), stable=True)  # the tops with m <= 1/2 first
    n_lower = n - jnp.sum(upper, dtype=order.dtype)
    lower_slots = (n_lower + per_block - 1) // per_block * per_block
    n_blocks = -(-n // per_block) + 1
    slot = jnp.arange(n_blocks * per_block, dtype=order.dtype)
    rank = jnp.where(slot < lower_slots, jnp.minimum(slot, n_lower - 1), n_lower + slot - lower_slots)
    source = order[jnp.clip(rank, 0, n - 1)]

    # The blocks take the tops' inputs, not their parts (which the side was read from): the closed
    # form's derivatives are taken from the inputs (see .derivatives).
    blocked = jax.tree.map(lambda x: x[source].reshape((n_blocks, per_block) + x.shape[1:]), flat)
    # With no top above 1/2 the last block holds copies of a top below: it runs the lower side too.
    # Its values are not used, but the upper side's formulas are not finite at such a top (measured),
    # and no block should compute non-finite numbers that derivatives pass through.
    block_upper = (jnp.arange(n_blocks, dtype=order.dtype) * per_block >= lower_slots) & (n_lower < n)

    def one_block(inputs):
        block, is_upper = inputs
        return jax.lax.cond(is_upper, lambda b: motion(b, t, "upper"), lambda b: motion(b, t, "lower"), block)

    outputs = jax.lax.map(one_block, (blocked, block_upper))
    # Back to the tops' order: the top of rank r (in ``order``) was evaluated in slot r (lower side)
    # or lower_slots + r - n_lower (upper side).
    rank_of_top = batching.inverse_permutation(order)
    slot_of_top = jnp.where(rank_of_top < n_lower, rank_of_top, lower_slots + rank_of_top - n_lower)
    return tuple(x.reshape((n_blocks * per_block,) + x.shape[2:])[slot_of_top] for x in outputs)


def _lagrange_failures(inertia, com):
    """The conditions of Lagrange's top that ``inertia`` and ``com`` violate (elementwise masks).

    ``|I1 - I2| <= 100 eps max(I1, I2)`` and ``|(com_x, com_y)| <= 100 eps |com|``: roundoff in moments
    or positions computed by the user passes, a physical asymmetry does not.
    """
    tol = 100 * float(jnp.finfo(inertia.dtype).eps)
    asymmetric = jnp.abs(inertia[..., 0] - inertia[..., 1]) > tol * jnp.maximum(
        jnp.abs(inertia[..., 0]), jnp.abs(inertia[..., 1])
    )
    off_axis = jnp.hypot(com[..., 0], com[..., 1]) > tol * jnp.linalg.norm(com, axis=-1)
    return asymmetric, off_axis


_ASYMMETRIC = (
    "accuracy='exact' for a HeavyTop is Lagrange's top: it needs equal transverse moments I1 = I2 "
    "(inertia about the pivot, (I1, I1, I3) with body z the symmetry axis){}. Use "
    "accuracy='precise' (or 'balanced') to integrate an asymmetric top."
)
_OFF_AXIS = (
    "accuracy='exact' for a HeavyTop is Lagrange's top: it needs the centre of mass on the body z "
    "axis, com = (0, 0, l) with l of either sign{}. Use accuracy='precise' (or 'balanced') to "
    "integrate a top whose centre of mass is off the symmetry axis."
)


def _lagrange_checked(inertia, com):
    """``inertia`` and ``com`` with the conditions of Lagrange's top checked at run time (values traced
    under jit or vmap; known ones are checked earlier, in :func:`_check_lagrange_top`)."""
    asymmetric, off_axis = _lagrange_failures(inertia, com)
    inertia = error_if(inertia, asymmetric, _ASYMMETRIC.format(""))
    com = error_if(com, off_axis, _OFF_AXIS.format(""))
    return inertia, com


def _check_lagrange_top(model, state0):
    """Trace-time checks of ``accuracy='exact'`` for a :class:`HeavyTop` (values where they are known)."""
    if model.torques:
        raise ValueError(
            "accuracy='exact' for a HeavyTop is Lagrange's top under gravity alone; it has no closed "
            "form with extra torques. Use accuracy='precise' (or 'balanced')."
        )
    if is_full_tensor(model.inertia):
        raise ValueError(
            "accuracy='exact' for a HeavyTop needs principal moments (..., 3) about the pivot, with "
            "body z the symmetry axis; diagonalise the tensor with rigidjax.principal_axes and express "
            "com and omega in those axes first."
        )
    if state0.orientation is None:
        raise ValueError(
            "HeavyTop needs an orientation: pass State(omega, orientation=q) with a unit quaternion q "
            "(e.g. rigidjax.quat_from_euler(angles))."
        )
    values = known_values((model.inertia, model.com))
    if values is None:
        return  # traced: checked at run time by _lagrange_checked
    inertia, com = (np.asarray(x, np.float64) for x in values)
    dtype = float_dtype(model.inertia, model.com)
    failures = evaluated_now(lambda: _lagrange_failures(jnp.asarray(inertia, dtype), jnp.asarray(com, dtype)))
    asymmetric, off_axis = (np.asarray(x) for x in failures)
    if np.any(asymmetric):
        bad = np.broadcast_to(inertia, asymmetric.shape + (3,))[asymmetric][0]
        raise ValueError(_ASYMMETRIC.format(f"; got I1 = {bad[0]:g}, I2 = {bad[1]:g}"))
    if np.any(off_axis):
        bad = np.broadcast_to(com, off_axis.shape + (3,))[off_axis][0]
        raise ValueError(_OFF_AXIS.format(f"; got com = ({bad[0]:g}, {bad[1]:g}, {bad[2]:g})"))


def simulate_exact(model, state0, ts, chunk_size: int | None = None):
    """``accuracy="exact"``: a closed form, no integration (torque-free bodies, Lagrange's top).
    ``chunk_size``: bodies evaluated together (blocks of them one after another; a positive ``int``,
    checked by ``simulate``); None: as many as :func:`block_elements` allows at this number of
    samples."""
    if isinstance(model, HeavyTop):
        _check_lagrange_top(model, state0)
        ts = check_times_shape(ts)
        leaves = (model.inertia, model.mass, model.com, model.gravity)
        dtype = float_dtype(state0.omega, state0.orientation, *leaves)
        # Constants of the user's jit stay constants (values to check now).
        top, omega0, q0, ts = evaluated_now(
            lambda: (
                HeavyTop(*(jnp.asarray(x, dtype) for x in leaves)),
                *(x.astype(dtype) for x in (state0.omega, state0.orientation, ts)),
            )
        )
        return _run_exact(top, omega0, q0, ts, chunk_size)
    if not model.torque_free:
        raise ValueError(
            "accuracy='exact' is a closed form: for torque-free bodies (a FreeBody, or a RigidBody "
            "without torques) and for Lagrange's top (a HeavyTop with I1 = I2 and the centre of mass on "
            f"the body z axis); got {type(model).__name__} with torques or a field."
        )
    if is_full_tensor(model.inertia):
        raise ValueError(
            "accuracy='exact' needs principal moments (..., 3); diagonalise the tensor with "
            "rigidjax.principal_axes and rotate omega into those axes first."
        )
    ts = check_times_shape(ts)
    dtype = float_dtype(state0.omega, state0.orientation, model.inertia)
    # Constants of the user's jit stay constants (values to check now).
    body, omega0, q0, ts = evaluated_now(
        lambda: (
            FreeBody(_cast(model.inertia, dtype)),
            _cast(state0.omega, dtype),
            None if state0.orientation is None else _cast(state0.orientation, dtype),
            _cast(ts, dtype),
        )
    )
    return _run_exact(body, omega0, q0, ts, chunk_size)


def _cast(x, dtype):
    """``x`` as a JAX array of ``dtype``; as it is where it is one (a conversion costs ~10-20 us of
    Python per call, as much as the closed form of a few hundred bodies)."""
    return x if isinstance(x, jax.Array) and x.dtype == dtype else jnp.asarray(x, dtype)


def _run_exact(model, omega0, q0, ts, chunk_size):
    if not is_traced(model, omega0, q0, ts):
        traj, failures = _exact_collected(model, omega0, q0, ts, chunk_size)
        if not is_traced(failures):  # traced: constants of the user's jit, which holds the program
            raise_collected(failures)
            return traj
    checked = _raise_on_bad_values(model, omega0, q0, ts)
    return _exact(model, omega0, q0, ts, chunk_size, checked, not is_differentiated(model, omega0, q0, ts))


def _raise_on_bad_values(model, omega0, q0, ts) -> bool:
    """The closed forms' inputs get the same ``ValueError`` as the integrators' where their values are
    known (concrete, or the primal values of an eager grad or jvp); returns whether they were
    checked. The closed form's program keeps its own checks for the others (jit, vmap)."""
    values = known_values((model, omega0, q0, ts))
    if values is None:
        return False
    checked_inputs(*values, None, 0.0)
    return True
