"""Derivatives of the closed forms as every sample's Jacobian, so that reverse mode stays cheap.

A closed form evaluates a few hundred elliptic and theta-series operations per sample. Reverse mode
through them transposes the forward derivative operation by operation and keeps thousands of
intermediates per sample: on 10^4 torque-free bodies (omega and q at one time) a gradient took 6.4 s,
850 forward evaluations, and 34 s to compile; Lagrange's top took 200 s to compile. Here the
derivative of ``motion`` is instead every sample's Jacobian, taken in forward mode (one direction per
component of each differentiated input, batched), contracted with the input tangents: the tangent is
linear in them through these few numbers per sample, and reverse mode transposes only the
contraction (the same gradient: 0.08 s, 10 forward evaluations). The torque-free omega alone, whose
reverse mode is cheap as it is, is not wrapped (see ``torque_free._motion_core``).
"""

from collections.abc import Callable, Sequence

import jax
import jax.numpy as jnp
from jax.custom_derivatives import SymbolicZero

from .barrier import tangents_held


def sample_jacobians(motion: Callable, components: Sequence[int]) -> Callable:
    """``motion(*inputs)`` (returning arrays of shape ``batch + (k,)``) whose derivative is every
    sample's Jacobian with respect to the differentiated inputs.

    ``components[i]`` is the length of input ``i``'s last axis, each of whose entries is a direction
    of the Jacobian (a vector per body: ``3`` for ``omega0``), or ``0`` for an input whose every
    element is one direction (a scalar per body or per sample: ``mass``, ``t``). Inputs without a
    tangent (symbolic zeros) add no direction. Each input's shape (without the last axis where
    ``components[i] > 0``) broadcasts against ``batch``, and each output sample must depend only on
    the input elements it is broadcast against (bodies and sample times do not interact): one
    direction then moves every body's component at once and yields every sample's column.

    Reverse mode keeps ``(sum of the differentiated components) x k`` numbers per sample and output:
    ``6 x 7`` for a free body's omega and q differentiated in inertia and ``omega0``.
    """
    wrapped = jax.custom_jvp(motion)

    def jvp(primals, tangents):
        directions, coefficients = [], []
        for index, (x, dx, count) in enumerate(zip(primals, tangents, components, strict=True)):
            if isinstance(dx, SymbolicZero):
                continue
            for k in range(max(count, 1)):
                direction = [jnp.zeros_like(p) for p in primals]
                direction[index] = jnp.zeros_like(x).at[..., k].set(1) if count else jnp.ones_like(x)
                directions.append(direction)
                coefficients.append(dx[..., k] if count else dx)
        if not directions:
            outputs = wrapped(*primals)
            return outputs, jax.tree.map(jnp.zeros_like, outputs)
        stacked = [jnp.stack([d[i] for d in directions]) for i in range(len(primals))]
        with tangents_held():
            outputs, columns = jax.vmap(lambda *d: jax.jvp(motion, primals, d), out_axes=(None, 0))(*stacked)
        batch = jax.tree.leaves(outputs)[0].shape[:-1]
        weights = jnp.stack([jnp.broadcast_to(c, batch) for c in coefficients])[..., None]
        return outputs, jax.tree.map(lambda column: jnp.sum(column * weights, axis=0), columns)

    wrapped.defjvp(jvp, symbolic_zeros=True)
    return wrapped
