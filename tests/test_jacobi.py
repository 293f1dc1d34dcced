"""The Jacobi functions with per-body parameters (``m`` of fewer axes than ``u``, as the closed forms
call them), the exact ``mod`` of integer-valued floats, and the materialising identity, against
mpmath, scipy and numpy."""

import re

import jax
import jax.numpy as jnp
import mpmath
import numpy as np
import pytest
import scipy.special as sc
from helpers import EPS64

from rigidjax._closed_form.barrier import _materialised
from rigidjax._closed_form.elliptic import _ellipj_checked
from rigidjax._closed_form.jacobi import _mod, _sin_cos

# Both sides of m = 1/2 (the ordinary and the complementary nome), the ends, and near the separatrix.
P_BODIES = np.array([1.0, 0.9, 0.5 + 2**-40, 0.5, 0.3, 0.02, 1e-6, 1e-12, 1e-200, 0.0])
U_SAMPLES = np.array([-37.0, -4.1, -0.3, 0.0, 0.2, 1.7, 3.0, 9.5, 55.0])

ellipj_bodies = jax.jit(lambda u, p: jnp.stack(_ellipj_checked(u, 1 - p, p)))


def _mp_jacobi(u, p):
    """(sn, cn, dn) at 40 digits from mpmath's ellipfun, with ``m = 1 - p`` formed exactly."""
    with mpmath.workdps(40):
        m = 1 - mpmath.mpf(float(p))
        return [float(mpmath.ellipfun(k, mpmath.mpf(float(u)), m=m)) for k in ("sn", "cn", "dn")]


def test_ellipj_with_per_body_parameters_matches_mpmath():
    # One parameter per body (n, 1) against samples (1, T), as the closed forms evaluate them.
    out = np.asarray(ellipj_bodies(jnp.asarray(U_SAMPLES)[None, :], jnp.asarray(P_BODIES)[:, None]))
    assert out.shape == (4, P_BODIES.size, U_SAMPLES.size)
    for i, p in enumerate(P_BODIES):
        for j, u in enumerate(U_SAMPLES):
            ref = np.array(_mp_jacobi(u, p))
            # eps (|f| + |u df/du|), as tests/test_elliptic.py measures it; |df/du| <= 1.
            scale = np.maximum(np.abs(ref) + abs(u), 1e-30)  # mpmath: sn(0) = -1e-47 at 40 digits
            err = np.abs(out[:3, i, j] - ref) / (EPS64 * scale)
            assert np.max(err) <= 8, (p, u, err)


def test_ellipj_per_body_equals_elementwise_and_scipy():
    rng = np.random.default_rng(11)
    m = rng.uniform(0, 1, (64, 1))
    u = rng.uniform(-30, 30, (64, 5))
    per_body = np.asarray(ellipj_bodies(jnp.asarray(u), jnp.asarray(1 - m)))
    elementwise = np.asarray(ellipj_bodies(jnp.asarray(u), jnp.asarray(np.broadcast_to(1 - m, u.shape))))
    # The same formulas; the compiler may contract them into fused multiply-adds differently.
    assert np.all(np.abs(per_body - elementwise) <= 4 * EPS64 * (1 + np.abs(u)))
    theirs = np.array(sc.ellipj(u, np.broadcast_to(m, u.shape)))
    # scipy's dn is off by up to ~70 ulp (tests/test_elliptic.py); sn, cn and am agree closely.
    tol = 8 * EPS64 * (1 + np.abs(u))
    for k in (0, 1, 3):
        assert np.all(np.abs(per_body[k] - theirs[k]) <= tol), k
    assert np.all(np.abs(per_body[2] - theirs[2]) <= 200 * EPS64 * (1 + np.abs(u)))


def test_ellipj_per_body_derivatives_match_elementwise():
    m = jnp.asarray([[0.2], [0.7], [1 - 1e-9]])
    u = jnp.asarray([[0.3, -2.0, 7.5]])

    def f(u, m):
        return jnp.sum(jnp.stack(_ellipj_checked(u, m, 1 - m)[:3]) ** 2 * jnp.arange(1.0, 4.0)[:, None, None])

    g_u, g_m = jax.grad(f, argnums=(0, 1))(u, m)
    full_u, full_m = jax.grad(f, argnums=(0, 1))(jnp.broadcast_to(u, (3, 3)), jnp.broadcast_to(m, (3, 3)))
    np.testing.assert_allclose(g_u, jnp.sum(full_u, 0, keepdims=True), rtol=1e-13, atol=1e-13)
    np.testing.assert_allclose(g_m, jnp.sum(full_m, 1, keepdims=True), rtol=1e-13, atol=1e-13)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_mod_is_exact_for_integer_valued_floats(dtype):
    k = np.array([-(2.0**23) + 1, -9, -4, -3, -1, -0.0, 0, 1, 2, 3, 5, 8, 2.0**23 - 1], dtype)
    for n in (2, 4):
        ours = np.asarray(jax.jit(_mod, static_argnums=1)(jnp.asarray(k), n))
        assert ours.dtype == dtype
        np.testing.assert_array_equal(ours, np.mod(k, n))
    # NaN, as jnp.mod, for NaN and infinite input.
    assert np.all(np.isnan(np.asarray(_mod(jnp.asarray([np.nan, np.inf, -np.inf], dtype), 2))))


def test_sin_cos_matches_numpy_across_quadrants():
    x = np.concatenate([np.linspace(-40, 40, 4001), [-np.pi, -np.pi / 2, 0.0, np.pi / 2, np.pi, 1e5]])
    s, c = jax.jit(_sin_cos)(jnp.asarray(x))
    # Within 2 ulp of 1 below 2^20 pi/2, a few ulp of x beyond (the conditioning).
    tol = 2 * EPS64 * np.maximum(1, np.abs(x) * (np.abs(x) > 2**20))
    assert np.all(np.abs(np.asarray(s) - np.sin(x)) <= tol)
    assert np.all(np.abs(np.asarray(c) - np.cos(x)) <= tol)


def test_materialised_is_the_identity_with_its_derivatives():
    x = jnp.asarray([[1.5, -2.0, 0.0], [np.inf, -0.0, 3.0]])
    y = jnp.asarray([True, False])
    for first in (1.5, np.nan):
        xs = (x.at[0, 0].set(first), y)
        out = jax.jit(_materialised)(xs)
        np.testing.assert_array_equal(out[0], xs[0])
        np.testing.assert_array_equal(out[1], xs[1])
        assert np.signbit(out[0][1, 1])
    assert _materialised((jnp.zeros((0, 3)),))[0].shape == (0, 3)

    def f(a):
        (b,) = _materialised((jnp.sin(a),))
        return jnp.sum(b * a)

    a = jnp.asarray([0.3, -1.2, 2.0])
    expected = np.cos(a) * a + np.sin(a)
    np.testing.assert_allclose(jax.grad(f)(a), expected, rtol=1e-15)
    np.testing.assert_allclose(jax.jacfwd(f)(a), expected, rtol=1e-15)
    batched = jax.vmap(jax.grad(f))(jnp.stack([a, 2 * a]))
    np.testing.assert_allclose(batched[1], np.cos(2 * a) * 2 * a + np.sin(2 * a), rtol=1e-15)


@pytest.mark.parametrize("order", ["boolean first", "floating first"])
def test_materialised_keeps_its_loop_whatever_the_first_array(order):
    """The arrays are held by a loop whose trip count XLA cannot know. It was read from the first
    array, ``x == x``, which XLA folds to true for a boolean: the loop was removed and every reader
    recomputed the arrays (the precession's per-body constants, led by a boolean). Reference: the
    compiled program's own text, which names a while loop only where one survived."""
    flags = jnp.asarray([True, False, True])
    values = jnp.asarray([0.5, -1.0, 2.0])
    xs = (flags, values) if order == "boolean first" else (values, flags)

    def held(a, b):
        return _materialised((a, jnp.exp(b) if b.dtype != jnp.bool_ else b))

    compiled = jax.jit(held).lower(*xs).compile().as_text()
    assert re.search(r"\bwhile\b", compiled), compiled[:2000]
    out = jax.jit(held)(*xs)
    exp = np.exp(np.asarray(values))
    want = (flags, exp) if order == "boolean first" else (values, flags)
    for got, expected in zip(out, want, strict=True):
        np.testing.assert_allclose(np.asarray(got), np.asarray(expected), rtol=1e-15)


def test_materialised_refuses_arrays_without_a_floating_one():
    """Without a floating array there is no trip count that XLA cannot know: the loop would be
    removed and nothing held, so it says so instead."""
    with pytest.raises(TypeError, match="floating-point array"):
        _materialised((jnp.asarray([1, 2]), jnp.asarray([True, False])))
