"""NaN-safe numerical primitives: norms and angles whose value and gradient stay finite at 0."""

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


def safe_norm(v, axis=-1, keepdims=False):
    """Euclidean norm whose gradient at the zero vector is 0 instead of NaN."""
    sq = jnp.sum(v * v, axis=axis, keepdims=keepdims)
    positive = sq > 0
    return jnp.where(positive, jnp.sqrt(jnp.where(positive, sq, jnp.ones_like(sq))), 0.0)


def safe_hypot(a, b):
    return safe_norm(jnp.stack([a, b], axis=-1))
