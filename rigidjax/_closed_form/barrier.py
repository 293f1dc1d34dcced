"""Arrays held in memory between two parts of a compiled program.

XLA on CPU fuses elementwise producers into their consumer and evaluates the fused expression once
per element of the consumer's output. Where the consumer stacks components (a quaternion, an
angular velocity in the body's axis order) or multiplies quaternions, every output component
recomputes the whole per-sample solution it reads, in scalar code (the stacked axis is the fastest
one). ``jax.lax.optimization_barrier`` and a ``cond`` do not stop this on CPU (both are gone before
fusion); a loop whose trip count XLA cannot know does.
"""

import jax
import jax.numpy as jnp


@jax.custom_jvp
def _materialised(arrays):
    """``arrays`` (a tuple), computed in full before any of their consumers runs.

    The identity: one pass of a loop that multiplies by one, with the trip count read at run time
    (0 where the first element is NaN, which returns the arrays as they are), so that XLA can
    neither remove the loop nor fuse across it. The tangents pass through unchanged (a custom JVP),
    so reverse mode sees no loop.
    """
    if not arrays or any(jnp.size(a) == 0 for a in arrays):
        return arrays
    first = jnp.ravel(arrays[0])[0]
    trips = (first == first).astype(jnp.int32)

    def body(_, xs):
        return tuple(x * trips.astype(x.dtype) for x in xs)

    return jax.lax.fori_loop(0, trips, body, tuple(arrays))


@_materialised.defjvp
def _materialised_jvp(primals, tangents):
    (arrays,), (dots,) = primals, tangents
    return _materialised(arrays), dots
