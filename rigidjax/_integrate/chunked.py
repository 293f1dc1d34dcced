"""A batch of bodies through the driver, chunk by chunk, and back into a :class:`Trajectory`.

Bodies are flattened and cut into chunks (:mod:`.batching`); each chunk is one ODE (its layout
chosen by a formulation, :mod:`.formulations`) solved by :func:`.driver.solve` with one shared step
size, accepted only when EVERY body in it meets the tolerance (a max norm over the chunk, so a fast
body cannot hide among slow ones).

Tolerances are dimensionless: under :class:`.formulations.ScaledODE` each body's angular velocity is
divided by a per-component scale (``model.omega_scale``: for a torque-free body, the largest value
each component reaches; otherwise |omega0|), and the quaternion is O(1), so ``rtol`` and ``atol``
mean the same thing for the Earth in SI units and for a 1e5 rad/s rotor.
"""

import math

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp

from .._closed_form.torque_free import motion_timing
from .._dynamics.inertia import principal_axes
from .._dynamics.state import State
from .._numerics import short_norm
from . import batching, driver
from .presets import FaultStopPIDController
from .trajectory import Trajectory, first_failed_sample


def max_norm(x):
    """Max norm of the scaled error over the chunk. NaN counts as infinitely large: a trial step so
    long that it overflows (the first step of a 1e4 rad/s body) is rejected and shortened, instead
    of turning the step size into NaN for good."""
    norm = jnp.max(jnp.abs(jnp.concatenate([jnp.ravel(leaf) for leaf in jax.tree_util.tree_leaves(x)])))
    return jnp.where(jnp.isnan(norm), jnp.inf, norm)


NON_FINITE = -1
"""A body's result code when its state turned non-finite although its chunk's solve went on (a
fixed-step solver has no error estimate to stop it)."""


def _omega_scales(model, leaves, flat, omega0, q0, duration, args):
    """Per-body, per-component angular-velocity scales (n, 3), never below 10 eps of the largest."""

    def scale_one(body_values, w, q):
        body = batching.body_model(model, leaves, body_values)
        return body.omega_scale(State(w, q), duration, args)

    sigma = jax.vmap(scale_one, in_axes=(0, 0, None if q0 is None else 0))(flat, omega0, q0)
    sigma = jax.lax.stop_gradient(sigma)
    peak = jnp.max(sigma, axis=-1, keepdims=True)
    floor = 10 * jnp.finfo(omega0.dtype).eps * peak
    return jnp.where(peak > 0, jnp.maximum(sigma, floor), jnp.ones_like(sigma))


PERIOD_GROUP_CHUNKS = 4
"""Chunks' worth of torque-free bodies of similar period that :func:`_chunk_order_keys` orders by
the time of their next flip."""


def _chunk_order_keys(model, leaves, flat, omega0, sigma, chunk_size):
    """The bodies' order into chunks (keys of :func:`.batching.plan_chunks`): decreasing speed, and
    for torque-free bodies, in speed classes a factor ``2^(1/4)`` wide, groups of
    ``PERIOD_GROUP_CHUNKS`` chunks of bodies of increasing period, each ordered by the time of the
    bodies' next flip (:func:`.motion_timing`). A chunk's step must satisfy its most demanding body
    at every moment; bodies that flip at the same times let the whole chunk take long steps in
    between. Measured with "balanced" against the order by speed alone: 10^4 tennis-racket bodies
    (speeds within 2 %, periods 10 - 25 s) started in phase, 126 -> 102 steps per chunk; the same
    bodies at random phases, 127 -> 115; 10^4 tumbling bodies of speeds 1 - 100 rad/s over 2 s,
    2388 -> 2327 steps in all."""
    speed = jnp.max(sigma, axis=-1)
    if not model.torque_free:
        return (-speed,)
    inertia = jax.lax.stop_gradient(flat[[leaf.label for leaf in leaves].index("inertia")])
    omega = jax.lax.stop_gradient(omega0)
    if inertia.ndim == 3:  # tensors: the timing from the principal moments and axes
        inertia, axes = principal_axes(inertia)
        omega = jnp.einsum("nji,nj->ni", axes, omega)
    period, next_flip = motion_timing(inertia, omega)
    speed_class = -jnp.floor(4 * jnp.log2(speed))
    # Groups of whole chunks in the order by speed class and period (a chunk straddles two groups
    # only where it straddles two speed classes).
    position = batching.inverse_permutation(batching.lexsort((period, speed_class)))
    return next_flip, position // (PERIOD_GROUP_CHUNKS * chunk_size), speed_class


def plan_bodies(model, omega0, q0, ts, args, formulation, chunk_size, sort):
    """The batch flattened to per-body arrays, each body's omega scales and the chunk plan:
    ``(batch, leaves, flat, omega0, q0, sigma, plan)``. The one place the chunks' body order is
    decided (:mod:`.progress` runs blocks of the same chunks)."""
    batch = batching.batch_shape(model, omega0, q0)
    leaves, flat = batching.flatten_model(model, batch, omega0.dtype)
    omega0 = batching.flatten(omega0, batch)
    q0 = None if q0 is None else batching.flatten(q0, batch)
    if formulation.uses_scale:
        sigma = _omega_scales(model, leaves, flat, omega0, q0, ts[-1] - ts[0], args)
    else:
        sigma = jnp.ones_like(omega0)
    n, shardable = math.prod(batch), ts.shape[0] > 1
    chunk, n_chunks, _ = batching.chunk_layout(n, chunk_size, shardable=shardable)  # groups: whole chunks
    # Without scales there is nothing to sort by; in one chunk, no order to choose (the keys would
    # only be traced, to be dropped again).
    sorted_ = sort and formulation.uses_scale and n_chunks > 1
    sort_keys = _chunk_order_keys(model, leaves, flat, omega0, sigma, chunk) if sorted_ else None
    plan = batching.plan_chunks(n, chunk_size, sort_keys, shardable=shardable)
    return batch, leaves, flat, omega0, q0, sigma, plan


def _kept_samples(omega, q):
    """Per body ``(bodies, T, .)``: the first sample that is not finite (``T`` if none), the samples
    from there on NaN (a failed chunk leaves its unreached samples at inf, a body whose state turned
    non-finite NaN: everything before the first bad sample is kept), the quaternions normalised and
    the largest deviation of their norm from 1 over the kept samples. Returns ``(omega, q,
    first_bad, q_norm_error)``."""
    n_times = omega.shape[-2]
    bad = ~jnp.all(jnp.isfinite(omega), axis=-1)
    if q is not None:
        bad = bad | ~jnp.all(jnp.isfinite(q), axis=-1)
    first_bad = first_failed_sample(bad)
    keep = jnp.arange(n_times) < first_bad[:, None]
    omega = jnp.where(keep[..., None], omega, jnp.nan)
    if q is None:
        return omega, None, first_bad, None
    q_norm = short_norm(q, keepdims=True)
    q_norm_error = jnp.max(jnp.where(keep, jnp.abs(q_norm[..., 0] - 1.0), 0.0), axis=-1)
    return omega, jnp.where(keep[..., None], q / q_norm, jnp.nan), first_bad, q_norm_error


def _bounded_pid(controller):
    """The PID controller whose steps :meth:`ScaledODE.step_bound` bounds, bare or inside diffrax's
    ``ClipStepSizeController`` (sample times as step ends): the presets' ``FaultStopPIDController``
    and a diffrax ``PIDController`` of one's own without a ``dtmax`` (one with a ``dtmax`` is used
    as given), or None for any other controller; and a function that puts a changed PID controller
    back in ``controller``'s place."""
    clipped = isinstance(controller, diffrax.ClipStepSizeController)
    inner = controller.controller if clipped else controller
    bounded = isinstance(inner, FaultStopPIDController) or (
        isinstance(inner, diffrax.PIDController) and inner.dtmax is None
    )

    def put_back(pid):
        return eqx.tree_at(lambda c: c.controller, controller, pid) if clipped else pid

    return (inner if bounded else None), put_back


def _with_dtmax(pid, bound):
    """``pid`` with its ``dtmax`` lowered to ``bound``."""
    dtmax = bound if pid.dtmax is None else jnp.minimum(pid.dtmax, bound)
    return eqx.tree_at(lambda c: c.dtmax, pid, dtmax, is_leaf=lambda x: x is None)


@eqx.debug.assert_max_traces(max_traces=None)  # counts traces, for the no-recompile tests
def _integrate_traced(
    model,
    omega0,
    q0,
    ts,
    args,
    controller,
    solver,
    adjoint,
    dt0,
    *,
    formulation,
    max_steps,
    chunk_size,
    sort,
):
    batch, leaves, flat, omega0, q0, sigma, plan = plan_bodies(
        model, omega0, q0, ts, args, formulation, chunk_size, sort
    )
    n_times = ts.shape[0]

    if n_times == 1:
        omega, q, first_bad, q_norm_error = _kept_samples(
            omega0[:, None, :], None if q0 is None else q0[:, None, :]
        )
        code = jnp.full((plan.n,), driver.SUCCESSFUL, jnp.int32)
        steps = jnp.zeros((plan.n_chunks,), jnp.int32)
    else:
        chunks = tuple(batching.to_chunks(plan, x) for x in (omega0, q0, sigma))
        chunks = ([batching.to_chunks(plan, v) for v in flat], *chunks)
        shell = model.replace_body_leaves(leaves, [None] * len(leaves))
        shared, static = eqx.partition((shell, args, ts, controller, solver, adjoint, dt0), eqx.is_array)

        def solve_chunk(chunk, shared):
            values, w0, cq0, s = chunk
            shell, args, ts, controller, solver, adjoint, dt0 = eqx.combine(shared, static)
            values = formulation.prepare(values, leaves)
            y0 = formulation.initial_state(values, leaves, w0, cq0, s)
            vector_field = formulation.vector_field(shell, leaves, values, s)
            first_step = dt0
            adaptive = not isinstance(controller, diffrax.ConstantStepSize | diffrax.StepTo)
            if first_step is None and adaptive and formulation.uses_scale:
                first_step = formulation.first_step(vector_field, y0, s, ts, args)
            pid, put_back = _bounded_pid(controller)
            if pid is not None:
                bound = formulation.step_bound(vector_field, y0, s, ts, args, pid.rtol, solver.order(None))
                controller = put_back(_with_dtmax(pid, bound))
                if first_step is not None:  # diffrax takes a given first step as it is
                    first_step = jnp.minimum(first_step, bound)
            solution = driver.solve(
                vector_field,
                formulation.chunk_solver(solver, values, leaves),
                y0,
                ts,
                stepsize_controller=controller,
                dt0=first_step,
                args=args,
                adjoint=adjoint,
                max_steps=max_steps,
                event=formulation.event(),
                save_fn=formulation.save_fn,
            )
            # Per chunk, while its samples are in cache, not in passes over the whole batch's
            # samples afterwards.
            kept = _kept_samples(*formulation.outputs(solution.ys, values, leaves, s))
            if q0 is None:  # a formulation may integrate an orientation the user did not ask for
                kept = (kept[0], None, kept[2], None)
            code = jnp.broadcast_to(solution.result, kept[2].shape)
            return (*kept, code), solution.num_steps

        per_body, steps = batching.map_chunks_into(solve_chunk, chunks, shared, plan)
        omega, q, first_bad, q_norm_error, code = per_body

    code = jnp.where((code == driver.SUCCESSFUL) & (first_bad < n_times), NON_FINITE, code)
    ok = code == driver.SUCCESSFUL
    return Trajectory(
        ts=ts,
        omega=omega.reshape(batch + (n_times, 3)),
        orientation=None if q is None else q.reshape(batch + (n_times, 4)),
        # As given (checked, cast), not broadcast: (3,) moments broadcast to a batch ending in 3
        # would read as a (..., 3, 3) tensor.
        model=model,
        success=ok.reshape(batch),
        stats={
            "num_steps": steps,
            "chunk_size": jnp.asarray(plan.chunk, jnp.int32),
            "quaternion_norm_error": None if q_norm_error is None else q_norm_error.reshape(batch),
            "result": code.reshape(batch),
            "first_failed_sample": first_bad.reshape(batch),
        },
    )


integrate = eqx.filter_jit(_integrate_traced)
"""The compiled batch integration: ``integrate(model, omega0, q0, ts, args, controller, solver,
adjoint, dt0, *, formulation, max_steps, chunk_size, sort) -> Trajectory``.

It raises nothing: the caller checks the inputs first and reports failures from
``stats["result"]``, so the program holds none of rigidjax's error callbacks and a failure can be
reported with its values (which body, when) outside it."""
