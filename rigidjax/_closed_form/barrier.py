"""Arrays held in memory between two parts of a compiled program.

XLA on CPU fuses elementwise producers into their consumer and evaluates the fused expression once
per element of the consumer's output. Where the consumer stacks components (a quaternion, an
angular velocity in the body's axis order) or multiplies quaternions, every output component
recomputes the whole per-sample solution it reads, in scalar code (the stacked axis is the fastest
one). ``jax.lax.optimization_barrier`` and a ``cond`` do not stop this on CPU (both are gone before
fusion); a loop whose trip count XLA cannot know does.
"""

import contextlib
import contextvars

import jax
import jax.numpy as jnp
import numpy as np

_TANGENTS_HELD = contextvars.ContextVar("tangents_held", default=False)


@contextlib.contextmanager
def tangents_held():
    """Forward-mode derivatives taken inside also hold their tangents in memory at each
    :func:`_materialised` (otherwise they pass through and every reader recomputes them: a closed
    form's Jacobian took 0.14 s instead of 8 ms on 10^3 bodies). Forward mode only: the loop that
    holds them has no transpose, so what is differentiated inside must not be transposed (see
    :func:`.derivatives.sample_jacobians`, whose reverse mode transposes only the contraction of the
    Jacobians taken inside)."""
    token = _TANGENTS_HELD.set(True)
    try:
        yield
    finally:
        _TANGENTS_HELD.reset(token)


@jax.custom_jvp
def _materialised(arrays):
    """``arrays`` (a tuple), computed in full before any of their consumers runs.

    The identity: one pass of a loop that multiplies by one, with the trip count read at run time
    (0 where the first element of the first floating array is NaN, which returns the arrays as they
    are), so that XLA can neither remove the loop nor fuse across it. The trip count is read from a
    floating array: ``x == x`` of an integer or boolean is known to XLA, which then removed the
    loop, and every reader recomputed the arrays (the precession's per-body constants, led by a
    boolean, at every sample). The tangents pass through unchanged (a custom JVP), so reverse mode
    sees no loop, except under :func:`tangents_held`.
    """
    if not arrays or any(jnp.size(a) == 0 for a in arrays):
        return arrays
    floating = [a for a in arrays if jnp.issubdtype(jnp.result_type(a), jnp.inexact)]
    if not floating:
        raise TypeError("_materialised needs a floating-point array to read its trip count from")
    first = jnp.ravel(floating[0])[0]
    trips = (first == first).astype(jnp.int32)

    def body(_, xs):
        return tuple(x * trips.astype(x.dtype) for x in xs)

    return jax.lax.fori_loop(0, trips, body, tuple(arrays))


@_materialised.defjvp
def _materialised_jvp(primals, tangents):
    (arrays,), (dots,) = primals, tangents
    if _TANGENTS_HELD.get() and all(jnp.issubdtype(d.dtype, jnp.inexact) for d in dots):
        held = _materialised(tuple(arrays) + tuple(dots))
        return held[: len(arrays)], held[len(arrays) :]
    return _materialised(arrays), dots


def _held_per_body(arrays, t):
    """``arrays`` of the bodies, read at the sample times ``t`` (broadcast against them), held by
    :func:`_materialised` where there are more samples than bodies. With one sample per body they
    are returned as they are: fused into their readers, they are computed once per sample anyway,
    and holding them cost two kernels per array."""
    samples = jnp.broadcast_shapes(jnp.shape(t), *(jnp.shape(a) for a in arrays))
    if max(int(np.prod(jnp.shape(a))) for a in arrays) >= int(np.prod(samples)):
        return tuple(arrays)
    return _materialised(tuple(arrays))
