"""Input checks shared by every public entry point: dtypes, shapes, finiteness, unit quaternions,
rotation matrices and sample times.

Two kinds of error, as everywhere in rigidjax: shape and dtype problems raise ``ValueError`` /
``TypeError`` while tracing; value problems (NaN, a non-unit quaternion, decreasing times) are
``eqx.error_if`` checks that work under ``jit`` and ``vmap``. Messages name the argument.
"""

import equinox as eqx
import jax.numpy as jnp
import numpy as np


def as_float_array(x, name: str = "array"):
    """Converts ``x`` to a JAX float array, keeping a float32/float64 dtype if it has one.

    Integer inputs become the default float dtype. Complex and boolean input is rejected with a
    ``TypeError`` naming ``name`` (a boolean array where numbers are expected is a mistake, not data).
    """
    x = jnp.asarray(x)
    if jnp.issubdtype(x.dtype, jnp.complexfloating):
        raise TypeError(f"{name} must be real, got dtype {x.dtype}.")
    if x.dtype == jnp.bool_:
        raise TypeError(f"{name} must be a real number array, got dtype bool.")
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


def is_full_tensor(inertia, name: str = "inertia") -> bool:
    """True when ``inertia`` is a ``(..., 3, 3)`` tensor, False for principal moments ``(..., 3)``;
    a ``ValueError`` naming ``name`` for any other shape."""
    shape = jnp.shape(inertia)
    if len(shape) >= 2 and shape[-2:] == (3, 3):
        return True
    if len(shape) >= 1 and shape[-1] == 3:
        return False
    raise ValueError(
        f"{name} must be principal moments of shape (..., 3) or a tensor of shape (..., 3, 3) "
        f"(kg m^2), got shape {tuple(shape)}."
    )


# --- run-time value checks of the public functions (eqx.error_if: they work under jit and vmap) ----


def unit_tolerance(dtype) -> float:
    """How far ``R R^T`` may be from ``1`` for a matrix to count as a rotation: ``1e-6`` in float64,
    ``1e-4`` in lower precision. The same tolerance as :func:`rigidjax.simulate` uses for the norm of
    ``state0.orientation``."""
    return 1e-6 if np.dtype(dtype) == np.float64 else 1e-4


def check_finite(x, name: str, where: str):
    """``x`` wrapped in a run-time check that all its entries are finite."""
    return eqx.error_if(x, ~jnp.all(jnp.isfinite(x)), f"{where}: {name} contains NaN or inf.")


def check_rotation_quaternion(q, name: str, where: str):
    """``q`` wrapped in run-time checks: finite, and with a norm that can be divided by (``|q|^2``
    neither 0 nor under- or overflowing). Such a ``q`` means the rotation of ``q / |q|``."""
    q = check_finite(q, name, where)
    sq = jnp.sum(q * q, axis=-1)
    return eqx.error_if(
        q,
        jnp.any(~jnp.isfinite(sq) | (sq < np.finfo(q.dtype).tiny)),
        f"{where}: {name} has zero norm (or one whose square under- or overflows): it is not a "
        "rotation. A rotation is a unit quaternion (w, x, y, z), e.g. (1, 0, 0, 0) for the identity.",
    )


def check_rotation_matrix(R, name: str, where: str):
    """``R`` wrapped in run-time checks: finite, ``max|R R^T - 1| <= unit_tolerance`` and ``det R > 0``."""
    R = check_finite(R, name, where)
    tol = unit_tolerance(R.dtype)
    gram = jnp.einsum("...ij,...kj->...ik", R, R)
    off = jnp.max(jnp.abs(gram - jnp.eye(3, dtype=R.dtype)), axis=(-2, -1))
    R = eqx.error_if(
        R,
        jnp.any(off > tol),
        f"{where}: {name} is not a rotation matrix (max |{name} {name}^T - 1| > {tol:g}); "
        "orthonormalise it first (e.g. the polar factor U V^T of its SVD).",
    )
    return eqx.error_if(
        R,
        jnp.any(jnp.linalg.det(R) <= 0),
        f"{where}: {name} has determinant -1: it is a reflection, not a rotation.",
    )
