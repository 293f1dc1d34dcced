"""NaN-safe numerical primitives: norms and angles whose value and gradient stay finite at 0, and
the symmetric 3x3 eigendecomposition whose derivative stays finite at degenerate moments."""

import jax
import jax.numpy as jnp
import numpy as np


def eps(dtype) -> float:
    return float(np.finfo(dtype).eps)


def safe_atan2(y, x):
    """``atan2`` that returns 0 with a zero (finite) gradient at ``x = y = 0``."""
    at_origin = (x == 0) & (y == 0)
    x_safe = jnp.where(at_origin, jnp.ones_like(x), x)
    y_safe = jnp.where(at_origin, jnp.zeros_like(y), y)
    return jnp.where(at_origin, jnp.zeros_like(x), jnp.arctan2(y_safe, x_safe))


def short_sum(x, axis=-1, keepdims=False):
    """``jnp.sum`` over a short axis (quaternions, vectors) as a sum of its slices: XLA on CPU hands a
    reduction over a short last axis to a library call of its own, which cost more than the arithmetic
    (10^4 quaternions' norm: ~0.4 ms against ~0.02 ms), and splits the computation around it."""
    axis = axis % x.ndim
    if not 0 < x.shape[axis] <= 8:
        return jnp.sum(x, axis=axis, keepdims=keepdims)
    return sum(jax.lax.index_in_dim(x, k, axis, keepdims=keepdims) for k in range(x.shape[axis]))


def short_norm(x, axis=-1, keepdims=False):
    """Euclidean norm over a short axis (see :func:`short_sum`)."""
    return jnp.sqrt(short_sum(x * x, axis, keepdims))


def safe_sqrt(x):
    """``sqrt(max(x, 0))`` whose derivative is 0 where ``x <= 0`` instead of infinite: the square root
    sees 1 there, so the unused branch passes no NaN or inf to a derivative."""
    positive = x > 0
    return jnp.where(positive, jnp.sqrt(jnp.where(positive, x, jnp.ones_like(x))), jnp.zeros_like(x))


def power_of_two_scaled(values, axis=-1):
    """``values`` times the power of two that brings the largest ``|value|`` over ``axis`` into
    ``[1/2, 1)``, per slice: exact, no rounding (a scale of ``2^k`` commutes with every product and
    quotient). Two factors, each a normal number built by ``ldexp``: one subnormal factor such as
    ``2^-1023`` is flushed to zero on CPU, and ``exp2`` is not exact in float32 (its rounding,
    amplified by ``1 / (C - A)``, cost the Earth's float32 wobble period 2e-5). The factor carries no
    derivative. Products of small moments in SI units underflow without it (float32: moments of
    1e-12 kg m^2), sums of large ones overflow."""
    largest = jax.lax.stop_gradient(jnp.max(jnp.abs(values), axis=axis, keepdims=True))
    _, exponent = jnp.frexp(jnp.where(largest > 0, largest, 1.0))
    half, one = exponent // 2, jnp.ones_like(largest)
    return values * jnp.ldexp(one, -half) * jnp.ldexp(one, half - exponent)


def safe_norm(v, axis=-1, keepdims=False):
    """Euclidean norm whose gradient at the zero vector is 0 instead of NaN."""
    return safe_sqrt(short_sum(v * v, axis=axis, keepdims=keepdims))


def safe_norm_of(*components):
    """:func:`safe_norm` of a vector given as separate component arrays: a stacked vector is what XLA
    on CPU would compute again for each reader of the result."""
    return safe_sqrt(sum(c * c for c in components))


def safe_hypot(a, b):
    return safe_norm(jnp.stack([a, b], axis=-1))


# Two moments closer than this many eps (relative to the largest |moment|) count as degenerate in
# the eigenvector derivative. Roundoff of a 3x3 ``eigh`` is a few eps, so 1e3 eps leaves a wide margin
# while still resolving physically distinct moments (1e-13 relative in float64, 1e-4 in float32).
_DEGENERACY_EPS = 1e3
# Relative tolerance (times eps times the largest |entry|) for a tensor to count as symmetric.
_SYMMETRY_EPS = 1e3
# Roundoff allowance (times eps times the trace) for the triangle inequality, which is an equality
# for a flat plate, and for the positivity of eigenvalues of a tensor.
_TRIANGLE_EPS = 1e2


def _swap(a):
    return jnp.swapaxes(a, -1, -2)


def _eigh3_impl(a):
    w, v = jnp.linalg.eigh(a, symmetrize_input=False)
    # Right-handed axes: flip the last column where the basis came out left-handed.
    sign = jnp.where(jnp.linalg.det(v) < 0, -1.0, 1.0).astype(v.dtype)
    v = jnp.concatenate([v[..., :2], v[..., 2:] * sign[..., None, None]], axis=-1)
    return w, v


_eigh3 = jax.custom_jvp(_eigh3_impl)
"""Ascending eigenvalues and right-handed eigenvectors (columns) of symmetric ``(..., 3, 3)`` input.

The JVP is the textbook one (``dw_i = v_i^T dA v_i``, ``dV = V (F o E)`` with ``F = V^T dA V`` and
``E_ij = 1 / (w_j - w_i)``), except that ``E_ij`` is set to 0 where ``|w_j - w_i|`` is below
``_DEGENERACY_EPS * eps * max|w|``: inside a degenerate eigenspace the eigenvectors are arbitrary and
the derivative of any basis-invariant (spectral) function does not depend on that choice.
"""


@_eigh3.defjvp
def _eigh3_jvp(primals, tangents):
    (a,) = primals
    (da,) = tangents
    w, v = _eigh3(a)  # the custom rule again, so higher derivatives are also safe
    da = 0.5 * (da + _swap(da))
    f = _swap(v) @ da @ v
    dw = jnp.diagonal(f, axis1=-2, axis2=-1)
    gap = w[..., None, :] - w[..., :, None]  # gap[i, j] = w_j - w_i
    scale = jnp.max(jnp.abs(w), axis=-1)
    tol = _DEGENERACY_EPS * eps(w.dtype) * scale
    keep = jnp.abs(gap) > tol[..., None, None]  # the diagonal (gap 0) is never kept
    inv_gap = jnp.where(keep, 1.0 / jnp.where(keep, gap, jnp.ones_like(gap)), jnp.zeros_like(gap))
    dv = v @ (f * inv_gap)
    return (w, v), (dw, dv)
