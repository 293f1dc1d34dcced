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

from .._checks import (
    StaticValue,
    check_times,
    check_times_shape,
    checks_done,
    collected_failures,
    compiled_once,
    error_if,
    evaluated_now,
    float_dtype,
    is_traced,
    known_values,
    packed_failures,
    raise_collected,
    times_in_dtype,
)
from .._closed_form.barrier import _materialised
from .._closed_form.frame import phase_unresolved
from .._closed_form.heavy_top import lagrange_top_motion
from .._closed_form.torque_free import _torque_free_motion, _torque_free_omega
from .._dynamics.gyrostat import Gyrostat
from .._dynamics.inertia import _symmetric_eigh
from .._dynamics.models import FreeBody, HeavyTop, keep_inertia_ndim
from .._kinematics.quaternion import _quat_conjugate, _quat_from_matrix, _quat_multiply
from .._numerics import short_norm
from . import batching
from .driver import is_differentiated
from .inputs import check_model, check_state, checked_inputs
from .trajectory import Trajectory, first_failed_sample

__all__ = ["simulate_exact"]


@eqx.filter_jit
def _exact(model, omega0, q0, ts, chunk_size: int | None, values_checked: bool):
    """The closed forms' program; ``values_checked``: the inputs' values were checked before it (no
    run-time checks, and so no host callback, in the program)."""
    with checks_done() if values_checked else contextlib.nullcontext():
        inputs = _exact_inputs(model, omega0, q0, ts)
    return _exact_motion(*inputs, chunk_size)


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
            lambda top: (top.inertia, top.com),
            model,
            _lagrange_checked(model.inertia, model.com, model.inertia_core_ndim == 2),
        )
    return model, omega0, q0, ts


def block_elements() -> int:
    """Body-samples per block of a closed form's evaluation. On CPU a block's few dozen
    ``(bodies, samples)`` intermediates then stay in the core's cache (XLA materialises them): 10^4
    bodies at 200 samples, medians of 7 alternated calls, the free body's omega and q 348 ms in one
    block against 223 ms in blocks of 655 bodies (2^17 body-samples), Lagrange's top 243 against
    200 ms; at 800 samples 1590 against 847 ms. On accelerators one block."""
    return 2**17 if jax.default_backend() == "cpu" else 2**62


def _exact_motion(model, omega0, q0, ts, chunk_size):
    """The closed form at ``ts``, in blocks of ``chunk_size`` bodies (None: :func:`block_elements`).

    Each block of Lagrange's tops evaluates both sides' theta series (``m`` below and above 1/2)
    with a mask. Sorting the tops into blocks of one side, each evaluating one side's series,
    compiled 2-3 s longer and ran no faster (2-core CPU, alternating runs):
    ``benchmarks/heavy_top_exact.py``'s 10^4 tops at 200 samples, compile 9.0-9.9 s against 7.1 s,
    run 0.224-0.230 s against 0.211-0.242 s; 1000 tops (2 blocks, each side padded to a whole
    block) 43-45 ms against 20-21 ms; the command's ``--accuracy exact`` heavy-top job 0.85-1.03 s
    against 0.48-0.50 s. Differentiated, the sorting's gathers and branches cost more still (10^4
    tops at 50 samples, ``jit(grad)``: 49 s of compile against 24 s)."""
    batch = batching.batch_shape(model, omega0, q0)
    n_bodies, n_times = math.prod(batch), ts.shape[0]
    heavy = isinstance(model, HeavyTop)
    tensor = model.inertia_core_ndim == 2
    per_body = {"inertia": (model.inertia, (3, 3) if tensor else (3,)), "omega0": (omega0, (3,))}
    if q0 is not None:
        per_body["q0"] = (q0, (4,))
    if heavy:
        per_body.update(com=(model.com, (3,)), mass=(model.mass, ()), gravity=(model.gravity, ()))
    flat = {
        name: jnp.broadcast_to(x, batch + core).reshape((n_bodies,) + core)
        for name, (x, core) in per_body.items()
    }
    # With two sample times (the state at one time) the first is the initial state itself and the
    # closed form is evaluated at the second only: a samples axis of one element, over which XLA
    # vectorises the bodies (it did not over a samples axis of two: 10^4 bodies' omega and q 8.4 ->
    # 4.4 ms). With more samples, writing the first one over cost up to 1.5x: all are evaluated.
    t = ts[1:] - ts[0] if n_times == 2 else ts - ts[0]

    def motion(bodies, t):
        """omega ``(bodies, samples, 3)``, the orientation ``(bodies, samples, 4)`` (or None) and the
        size of the closed form's phases ``(bodies, samples)`` at the times ``t`` after the first."""
        first_omega = bodies["omega0"]
        first_q = bodies.get("q0")  # checked and normalised by _exact_inputs
        if n_times == 1:
            return (
                first_omega[:, None],
                None if q0 is None else first_q[:, None],
                jnp.zeros_like(first_omega[:, :1]),
            )
        if heavy:
            omega, q, phase = _lagrange_top(bodies, t, tensor)
        else:
            omega, q, phase = _torque_free(bodies, t)
        if n_times == 2:
            # Computed in full before the stacking (see _closed_form.barrier): 10^4 bodies' omega
            # and q 5.5 -> 4.0 ms.
            omega, q = _materialised((omega, q)) if q is not None else (_materialised((omega,))[0], None)
            omega = jnp.stack([first_omega, omega[:, 0]], axis=1)
            phase = jnp.stack([jnp.zeros_like(phase[:, 0]), phase[:, 0]], axis=1)
            return omega, None if q is None else jnp.stack([first_q, q[:, 0]], axis=1), phase
        return omega, q, phase

    per_block = max(1, block_elements() // max(n_times, 1)) if chunk_size is None else chunk_size
    block = min(per_block, n_bodies)
    if n_bodies <= per_block:
        omega, orientation, phase = motion(flat, t)
    else:
        block = batching.plan_chunks(n_bodies, per_block, shardable=False).chunk
        omega, orientation, phase = _plain_blocks(motion, flat, t, block, n_times)
    # A body has failed (success False, as an integrated body's would be) where a sample is not
    # finite (inputs beyond what the dtype can evaluate, such as an angular momentum whose square
    # overflows) or the closed form's phase is beyond what the dtype resolves (the result is noise).
    bad = ~jnp.all(jnp.isfinite(omega), axis=-1) | phase_unresolved(phase)
    if orientation is not None:
        bad = bad | ~jnp.all(jnp.isfinite(orientation), axis=-1)
    first_bad = first_failed_sample(bad)
    success = first_bad == n_times
    omega = omega.reshape(batch + omega.shape[1:])
    if orientation is not None:
        orientation = orientation.reshape(batch + orientation.shape[1:])
    return Trajectory(
        ts=ts,
        omega=omega,
        orientation=orientation,
        model=model,
        success=success.reshape(batch),
        stats={
            "num_steps": jnp.zeros((), jnp.int32),
            "chunk_size": jnp.asarray(block, jnp.int32),
            "first_failed_sample": first_bad.reshape(batch),
            # Nothing normalises the closed forms' quaternions; Trajectory.invariants measures their
            # norm from the samples when asked. Computed here, alongside the samples, it cost 15-20 %
            # of the evaluation on CPU (10^4 bodies at 2 samples 9.8 -> 8.5 ms, 655 at 200
            # 17.7 -> 14.3 ms): XLA then writes each component of q to memory a second time.
            "quaternion_norm_error": None,
        },
    )


def nan_from_first_failure(traj: Trajectory) -> Trajectory:
    """``traj`` with each failed body's samples NaN from its first failed sample on, as an
    integrated body's are (``throw=False``). A separate pass over the samples, so not part of the
    closed form's program, whose successful runs would pay for it (a copy of every sample: 10^4
    bodies at 50 samples ~18 % slower); with concrete values and no failure, nothing is done."""
    if not isinstance(traj.success, jax.core.Tracer) and bool(np.all(np.asarray(traj.success))):
        return traj
    n_times = traj.ts.shape[0]
    keep = jnp.arange(n_times) < traj.stats["first_failed_sample"][..., None]
    blank = lambda x: None if x is None else jnp.where(keep[..., None], x, jnp.nan)  # noqa: E731
    return eqx.tree_at(
        lambda t: (t.omega, t.orientation),
        traj,
        (blank(traj.omega), blank(traj.orientation)),
        is_leaf=lambda x: x is None,
    )


_TOP_INPUTS = ("inertia", "mass", "com", "gravity", "omega0", "q0")
"""Lagrange's top's per-body inputs, in the order of :func:`.lagrange_top_motion`'s arguments."""


def _into_axes(axes, omega0, q0):
    """``omega0`` and ``q0`` of bodies seen in ``axes`` (``(n, 3, 3)``, columns: the axes' body-frame
    components, right-handed), and the axes' quaternion. A body given by a tensor turns as the body
    of its moments in those axes does: the closed form runs there and :func:`_out_of_axes` turns its
    omega and q back."""
    axes_q = _quat_from_matrix(axes)
    omega0 = jnp.einsum("nji,nj->ni", axes, omega0)
    return omega0, None if q0 is None else _quat_multiply(q0, axes_q), axes_q


def _out_of_axes(axes, axes_q, omega, q):
    """omega ``(n, samples, 3)`` and q (or None) of :func:`_into_axes`'s frame in the body axes."""
    omega = jnp.einsum("nij,nsj->nsi", axes, omega)
    return omega, None if q is None else _quat_multiply(q, _quat_conjugate(axes_q)[:, None])


def _torque_free(bodies, t):
    """omega, the orientation (or None) and the phases of torque-free bodies (per body ``inertia``,
    ``omega0`` and ``q0``, principal moments ``(n, 3)`` or tensors ``(n, 3, 3)``) at ``t``. A tensor's
    closed form runs in its principal axes (its eigendecomposition; ``simulate`` refuses a derivative
    with respect to the tensor here, which the axes do not carry where moments coincide)."""
    inertia, omega0, q0 = bodies["inertia"], bodies["omega0"], bodies.get("q0")
    if inertia.ndim == 3:
        inertia, axes = _symmetric_eigh(inertia)
        omega0, q0, axes_q = _into_axes(axes, omega0, q0)
    if q0 is None:
        (omega, phase), q = (
            _torque_free_omega(inertia[:, None], omega0[:, None], t, checked=False, phases=True),
            None,
        )
    else:
        omega, q, phase = _torque_free_motion(
            inertia[:, None], omega0[:, None], q0[:, None], t, checked=False, phases=True
        )
    if bodies["inertia"].ndim == 3:
        omega, q = _out_of_axes(axes, axes_q, omega, q)
    return omega, q, phase


def _lagrange_axes(tensor, com):
    """The axes (``(..., 3, 3)``, columns, right-handed) in which a top given by its ``tensor`` about
    the pivot is Lagrange's, with its symmetry axis third: the line through the centre of mass
    (completed by the body axis least aligned with it), or where ``com = 0`` the principal axes with
    the moment that differs from the other two third."""
    length = short_norm(com, keepdims=True)
    along = length > 0
    z = com / jnp.where(along, length, 1.0)
    helper = jax.nn.one_hot(jnp.argmin(jnp.abs(z), axis=-1), 3, dtype=com.dtype)
    x = helper - jnp.sum(helper * z, axis=-1, keepdims=True) * z
    x = x / short_norm(x, keepdims=True)
    from_com = jnp.stack([x, jnp.cross(z, x), z], axis=-1)
    moments, principal = _symmetric_eigh(tensor)
    odd_first = moments[..., 1] - moments[..., 0] > moments[..., 2] - moments[..., 1]
    from_moments = jnp.where(odd_first[..., None, None], principal[..., :, (1, 2, 0)], principal)
    return jnp.where(along[..., None], from_com, from_moments)


def _in_lagrange_axes(tensor, com):
    """``(axes, tensor, com)``: :func:`_lagrange_axes` and the tensor and com seen in them."""
    axes = _lagrange_axes(tensor, com)
    turned = jnp.einsum("...ji,...jk,...kl->...il", axes, tensor, axes)
    return axes, turned, jnp.einsum("...ji,...j->...i", axes, com)


def _lagrange_top(bodies, t, tensor: bool):
    """omega, q and the phases of Lagrange's tops (per body inputs of :data:`_TOP_INPUTS`) at ``t``;
    a top given by its tensor about the pivot in :func:`_lagrange_axes` (``simulate`` refuses a
    derivative with respect to that tensor or com, which turn the axes)."""
    top = dict(bodies)
    if tensor:
        axes, turned, top["com"] = _in_lagrange_axes(bodies["inertia"], bodies["com"])
        top["inertia"] = jnp.diagonal(turned, axis1=-2, axis2=-1)
        top["omega0"], top["q0"], axes_q = _into_axes(axes, bodies["omega0"], bodies["q0"])
    omega, q, phase = lagrange_top_motion(*(top[name][:, None] for name in _TOP_INPUTS), t, phases=True)
    if tensor:
        omega, q = _out_of_axes(axes, axes_q, omega, q)
    return omega, q, phase


def _plain_blocks(motion, flat, t, block, n_times):
    """``motion`` of the bodies in blocks of ``block`` bodies in a loop, each block's samples written
    in place into arrays of all the bodies. Where the blocks do not divide the bodies, the last block
    starts early and overlaps the one before it (those bodies are evaluated twice, to the same
    values). Stacked blocks (``lax.map``) with the last one padded were cut to the bodies afterwards:
    a second copy of every sample (10^6 free bodies at 64 samples, omega and q: a peak of 8.4 GB of
    memory against 4.9 GB here, 3.6 GB of them the samples)."""
    n = flat["omega0"].shape[0]
    # The shapes of motion's results, known here: jax.eval_shape traced the closed form a second
    # time (and a jit of motion, to reuse that trace, compiled its derivatives 0.4 s longer).
    zeros = lambda *shape: jnp.zeros((n, n_times) + shape, flat["omega0"].dtype)  # noqa: E731
    outputs = (zeros(3), zeros(4) if "q0" in flat else None, zeros())

    def one_block(i, outputs):
        start = jnp.minimum(i * block, n - block)
        bodies = {name: jax.lax.dynamic_slice_in_dim(x, start, block) for name, x in flat.items()}
        return jax.tree.map(
            lambda whole, part: jax.lax.dynamic_update_slice_in_dim(whole, part, start, 0),
            outputs,
            motion(bodies, t),
        )

    return jax.lax.fori_loop(0, -(-n // block), one_block, outputs)


def _lagrange_tolerance(dtype) -> float:
    """The relative deviation from Lagrange's top that passes as roundoff: ``100 eps``."""
    return 100 * float(jnp.finfo(dtype).eps)


def _lagrange_deviations(inertia, com, tensor: bool = False):
    """How far ``inertia`` and ``com`` are from Lagrange's top, relative (elementwise): the transverse
    moments' difference ``|I1 - I2| / max(I1, I2)`` and com's distance from the axis
    ``|(com_x, com_y)| / |com|``. A ``tensor`` (about the pivot) is seen in :func:`_lagrange_axes`:
    its first measure also counts the products of inertia there, and com lies on the axis."""
    if tensor:
        _, turned, com = _in_lagrange_axes(inertia, com)
        inertia = jnp.diagonal(turned, axis1=-2, axis2=-1)
        products = jnp.stack([turned[..., 0, 1], turned[..., 0, 2], turned[..., 1, 2]], axis=-1)
        products = jnp.max(jnp.abs(products), axis=-1)
    transverse = jnp.maximum(jnp.abs(inertia[..., 0]), jnp.abs(inertia[..., 1]))
    asymmetry = jnp.abs(inertia[..., 0] - inertia[..., 1])
    if tensor:
        asymmetry = jnp.maximum(asymmetry, products)
    length = jnp.linalg.norm(com, axis=-1)
    off_axis = jnp.hypot(com[..., 0], com[..., 1])
    transverse, length = (jnp.where(x > 0, x, jnp.ones_like(x)) for x in (transverse, length))
    return asymmetry / transverse, off_axis / length


_DEVIATIONS = {False: _lagrange_deviations, True: functools.partial(_lagrange_deviations, tensor=True)}


def _lagrange_failures(inertia, com, tensor: bool = False):
    """The conditions of Lagrange's top that ``inertia`` and ``com`` violate (elementwise masks):
    each deviation of :func:`_lagrange_deviations` at most ``100 eps``, so that roundoff in moments or
    positions computed by the user passes and a physical asymmetry does not."""
    tol = _lagrange_tolerance(inertia.dtype)
    return tuple(deviation > tol for deviation in _lagrange_deviations(inertia, com, tensor))


_ASYMMETRIC = (
    "accuracy='exact' for a HeavyTop is Lagrange's top: it needs equal transverse moments I1 = I2 "
    "(inertia about the pivot, (I1, I1, I3) with body z the symmetry axis){}. Use "
    "accuracy='precise' (or 'balanced') to integrate an asymmetric top."
)
_ASYMMETRIC_TENSOR = (
    "accuracy='exact' for a HeavyTop is Lagrange's top: given as a tensor about the pivot, it needs "
    "the tensor symmetric about the line from the pivot through the centre of mass (equal moments "
    "about every axis across it, no products of inertia with it){}. Use accuracy='precise' (or "
    "'balanced') to integrate an asymmetric top."
)
_OFF_AXIS = (
    "accuracy='exact' for a HeavyTop is Lagrange's top: it needs the centre of mass on the body z "
    "axis, com = (0, 0, l) with l of either sign{}. Use accuracy='precise' (or 'balanced') to "
    "integrate a top whose centre of mass is off the symmetry axis."
)


def _lagrange_checked(inertia, com, tensor: bool):
    """``inertia`` and ``com`` with the conditions of Lagrange's top checked at run time (values traced
    under jit or vmap; known ones are checked earlier, in :func:`_check_lagrange_top`)."""
    asymmetric, off_axis = _lagrange_failures(inertia, com, tensor)
    inertia = error_if(inertia, asymmetric, (_ASYMMETRIC_TENSOR if tensor else _ASYMMETRIC).format(""))
    com = error_if(com, off_axis, _OFF_AXIS.format(""))
    return inertia, com


def _check_lagrange_top(model, state0):
    """Trace-time checks of ``accuracy='exact'`` for a :class:`HeavyTop` (values where they are known)."""
    if model.torques:
        raise ValueError(
            "accuracy='exact' for a HeavyTop is Lagrange's top under gravity alone; it has no closed "
            "form with extra torques. Use accuracy='precise' (or 'balanced')."
        )
    tensor = model.inertia_core_ndim == 2
    if tensor and (is_differentiated(model.inertia) or is_differentiated(model.com)):
        raise ValueError(
            "accuracy='exact' for a HeavyTop given as an inertia tensor evaluates the closed form in "
            "the axes of its symmetry, which turn with the tensor and com: it has no derivative with "
            "respect to them. Differentiate with accuracy='precise' (or 'balanced'), or pass principal "
            "moments (I1, I1, I3) about the pivot with com = (0, 0, l) and differentiate those."
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
    # One program (operation by operation: nine for each new batch shape).
    deviations = evaluated_now(
        lambda: compiled_once(_DEVIATIONS[tensor])(jnp.asarray(inertia, dtype), jnp.asarray(com, dtype))
    )
    # The tolerance and the relative deviation are printed too: I1 and I2 that differ by 1e-13 read
    # the same at a few significant digits.
    tol = _lagrange_tolerance(dtype)
    asymmetric, off_axis = (np.asarray(x) > tol for x in deviations)
    if tensor and np.any(asymmetric):
        relative = float(np.max(np.asarray(deviations[0])))
        raise ValueError(
            _ASYMMETRIC_TENSOR.format(
                f"; got a tensor that departs from that symmetry by {relative:.2g} of its transverse "
                f"moment, more than the roundoff of {tol:.2g} ({dtype}) that passes"
            )
        )
    if np.any(asymmetric):
        bad = np.broadcast_to(inertia, asymmetric.shape + (3,))[asymmetric][0]
        relative = abs(bad[0] - bad[1]) / max(abs(bad[0]), abs(bad[1]))
        raise ValueError(
            _ASYMMETRIC.format(
                f"; got I1 = {float(bad[0])!r}, I2 = {float(bad[1])!r}, which differ by "
                f"{relative:.2g} of the larger, more than the roundoff of {tol:.2g} ({dtype}) that passes"
            )
        )
    if np.any(off_axis):
        bad = np.broadcast_to(com, off_axis.shape + (3,))[off_axis][0]
        relative = np.hypot(bad[0], bad[1]) / np.linalg.norm(bad)
        raise ValueError(
            _OFF_AXIS.format(
                f"; got com = ({bad[0]:g}, {bad[1]:g}, {bad[2]:g}), off the axis by {relative:.2g} of "
                f"|com|, more than the roundoff of {tol:.2g} ({dtype}) that passes"
            )
        )


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
        ts = times_in_dtype(ts, dtype)
        # Constants of the user's jit stay constants (values to check now).
        top, omega0, q0, ts = evaluated_now(
            lambda: (
                keep_inertia_ndim(HeavyTop(*(jnp.asarray(x, dtype) for x in leaves)), model),
                *(x.astype(dtype) for x in (state0.omega, state0.orientation, ts)),
            )
        )
        return _run_exact(top, omega0, q0, ts, chunk_size)
    if isinstance(model, Gyrostat):
        raise ValueError(
            "accuracy='exact' is a closed form for torque-free rigid bodies and Lagrange's top; a "
            "Gyrostat's rotors change the motion and have none here: use accuracy='balanced' or "
            "'precise'."
        )
    if not model.torque_free:
        raise ValueError(
            "accuracy='exact' is a closed form: for torque-free bodies (a FreeBody, or a RigidBody "
            "without torques) and for Lagrange's top (a HeavyTop with I1 = I2 and the centre of mass on "
            f"the body z axis); got {type(model).__name__} with torques or a field."
        )
    if model.inertia_core_ndim == 2 and is_differentiated(model.inertia):
        raise ValueError(
            "accuracy='exact' with an inertia tensor evaluates the closed form in the tensor's "
            "principal axes, which have no derivative where two moments coincide: differentiate with "
            "respect to the tensor with accuracy='precise' (or 'balanced'), or pass principal moments "
            "(..., 3) and differentiate those."
        )
    ts = check_times_shape(ts)
    dtype = float_dtype(state0.omega, state0.orientation, model.inertia)
    ts = times_in_dtype(ts, dtype)
    # Constants of the user's jit stay constants (values to check now).
    body, omega0, q0, ts = evaluated_now(
        lambda: (
            keep_inertia_ndim(FreeBody(_cast(model.inertia, dtype)), model),
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
    return _exact(model, omega0, q0, ts, chunk_size, checked)


def _raise_on_bad_values(model, omega0, q0, ts) -> bool:
    """The closed forms' inputs get the same ``ValueError`` as the integrators' where their values are
    known (concrete, or the primal values of an eager grad or jvp); returns whether they were
    checked. The closed form's program keeps its own checks for the others (jit, vmap)."""
    values = known_values((model, omega0, q0, ts))
    if values is None:
        return False
    checked_inputs(*values, None, 0.0)
    return True
