"""The NaN-safe numerical primitives: sums and norms over short axes, against NumPy."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from rigidjax._numerics import safe_norm, safe_norm_of, safe_sqrt, short_norm, short_sum


@pytest.mark.parametrize(
    "shape, axis", [((5, 3), -1), ((5, 4), 1), ((4, 2, 3), 0), ((2, 12), -1), ((3, 0), -1), ((7,), 0)]
)
@pytest.mark.parametrize("keepdims", [False, True])
def test_short_sum_and_norm_match_numpy(shape, axis, keepdims):
    x = np.random.default_rng(0).normal(size=shape)
    np.testing.assert_allclose(
        short_sum(jnp.asarray(x), axis, keepdims), np.sum(x, axis, keepdims=keepdims), rtol=1e-14
    )
    expected = np.linalg.norm(x, axis=axis, keepdims=keepdims)
    np.testing.assert_allclose(short_norm(jnp.asarray(x), axis, keepdims), expected, rtol=1e-14)
    np.testing.assert_allclose(safe_norm(jnp.asarray(x), axis, keepdims), expected, rtol=1e-14)


def test_safe_norm_gradient_is_zero_at_the_zero_vector_and_exact_elsewhere():
    np.testing.assert_array_equal(jax.grad(safe_norm)(jnp.zeros(4)), np.zeros(4))
    v = jnp.array([3.0, 4.0, 12.0])
    np.testing.assert_allclose(jax.grad(safe_norm)(v), np.asarray(v) / 13.0, rtol=1e-15)


def test_safe_sqrt_and_norm_of_components_match_numpy_with_finite_gradients_at_zero():
    x = np.random.default_rng(1).normal(size=(3, 6))
    np.testing.assert_allclose(safe_sqrt(jnp.asarray(x)), np.sqrt(np.maximum(x, 0)), rtol=1e-15)
    np.testing.assert_allclose(safe_norm_of(*jnp.asarray(x)), np.linalg.norm(x, axis=0), rtol=1e-14)
    # d/dx sqrt(x) = 1 / (2 sqrt(x)) where x > 0; 0 (not inf or NaN) at and below 0.
    points = jnp.array([4.0, 0.0, -1.0])
    np.testing.assert_array_equal(jax.vmap(jax.grad(safe_sqrt))(points), [0.25, 0.0, 0.0])
    np.testing.assert_array_equal(jax.grad(lambda a, b: safe_norm_of(a, b), (0, 1))(0.0, 0.0), (0.0, 0.0))
    np.testing.assert_allclose(
        jax.grad(lambda a, b: safe_norm_of(a, b), (0, 1))(3.0, 4.0), (0.6, 0.8), rtol=1e-15
    )
