"""Small numerical helpers shared by the modules: dtype handling and NaN-safe primitives."""

import jax.numpy as jnp
import numpy as np


def as_float_array(x, name: str = "array"):
    """Converts ``x`` to a JAX float array, keeping a float32/float64 dtype if it has one.

    Integer or boolean inputs become the default float dtype. Complex input is rejected by name.
    """
    x = jnp.asarray(x)
    if jnp.issubdtype(x.dtype, jnp.complexfloating):
        raise TypeError(f"{name} must be real, got dtype {x.dtype}.")
    if not jnp.issubdtype(x.dtype, jnp.floating):
        x = x.astype(jnp.result_type(float))
    return x


def common_float(*arrays, names=None):
    """Converts all inputs to float arrays of one common dtype (the widest float among them)."""
    names = names or [f"argument {i}" for i in range(len(arrays))]
    arrays = [as_float_array(a, n) for a, n in zip(arrays, names, strict=True)]
    # numpy's promotion, not jax's: widening float32 to float64 here is deliberate, and must not
    # depend on the user's jax_numpy_dtype_promotion setting.
    dtype = np.result_type(*[np.dtype(a.dtype) for a in arrays])
    return [a.astype(dtype) for a in arrays]


def check_last_axis(x, size: int, name: str):
    if x.ndim < 1 or x.shape[-1] != size:
        raise ValueError(f"{name} must have shape (..., {size}), got shape {tuple(x.shape)}.")


def check_last_two_axes(x, name: str):
    if x.ndim < 2 or x.shape[-2:] != (3, 3):
        raise ValueError(f"{name} must have shape (..., 3, 3), got shape {tuple(x.shape)}.")


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
