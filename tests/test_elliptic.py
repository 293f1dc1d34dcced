"""Elliptic integrals and Jacobi elliptic functions against scipy and mpmath, in float64 and float32.

Errors are measured in units of the float's eps. For the Jacobi functions the unit is eps times
``|f| + |u df/du|``: the functions are evaluated at ``u`` times a computed ``pi / (2 K)``, so a
relative error of ``eps`` in the argument is unavoidable and its effect grows with ``|u|`` (a cn near
one of its zeros, or a cn ~ sech(u) near m = 1, cannot be relatively accurate to better than that).

The functions are compiled once per dtype: ``call`` pads every batch to a power-of-two size.
"""

import functools

import jax
import jax.numpy as jnp
import mpmath
import numpy as np
import pytest
import scipy.special as sc
from helpers import EPS32, EPS64

from rigidjax.elliptic import ellipe, ellipeinc, ellipj, ellipj_m1, ellipk, ellipkinc, ellipkm1, elliprj


def _stacked(f):
    return lambda *args: jnp.stack(f(*args))


JIT = {
    "ellipk": jax.jit(ellipk),
    "ellipkm1": jax.jit(ellipkm1),
    "ellipe": jax.jit(ellipe),
    "ellipkinc": jax.jit(ellipkinc),
    "ellipeinc": jax.jit(ellipeinc),
    "ellipj": jax.jit(_stacked(ellipj)),
    "ellipj_m1": jax.jit(_stacked(ellipj_m1)),
    # Derivatives, batched: d/du and d/dm (or d/dp) of (sn, cn, dn, am), each of shape (n, 4).
    "jac_ellipj": jax.jit(jax.vmap(jax.jacfwd(_stacked(ellipj), argnums=(0, 1)))),
    "jac_ellipj_m1": jax.jit(jax.vmap(jax.jacfwd(_stacked(ellipj_m1), argnums=(0, 1)))),
    "jacrev_ellipj": jax.jit(jax.vmap(jax.jacrev(_stacked(ellipj), argnums=(0, 1)))),
    "grad_ellipk": jax.jit(jax.vmap(jax.grad(ellipk))),
    "grad_ellipkm1": jax.jit(jax.vmap(jax.grad(ellipkm1))),
    "grad_ellipe": jax.jit(jax.vmap(jax.grad(ellipe))),
    "grad_ellipkinc": jax.jit(jax.vmap(jax.grad(ellipkinc, argnums=(0, 1)))),
    "grad_ellipeinc": jax.jit(jax.vmap(jax.grad(ellipeinc, argnums=(0, 1)))),
    "jac_ellipkinc": jax.jit(jax.vmap(jax.jacfwd(ellipkinc, argnums=(0, 1)))),
    "jac_ellipeinc": jax.jit(jax.vmap(jax.jacfwd(ellipeinc, argnums=(0, 1)))),
}


def call(name, *args):
    """``JIT[name]`` elementwise on broadcast numpy arguments, as numpy; batch axes come first.

    Inputs are flattened and padded to a power of two (at least 64) with their first element, so that
    all calls of one function and dtype share a handful of compilations.
    """
    args = np.broadcast_arrays(*[np.asarray(a) for a in args])
    shape, n = args[0].shape, args[0].size
    size = max(64, 1 << (n - 1).bit_length())
    padded = [
        jnp.asarray(np.concatenate([a.ravel(), np.full(size - n, a.ravel()[0], a.dtype)])) for a in args
    ]
    out = JIT[name](*padded)

    def unpad(x):
        x = np.asarray(x)
        if x.shape[:1] == (size,):  # batch axis first (vmap)
            return x[:n].reshape(shape + x.shape[1:])
        return x[:, :n].reshape(x.shape[:1] + shape)  # stacked (sn, cn, dn, am) first

    return jax.tree.map(unpad, out)


# 1 - m for the grids: moderate, then right up to the separatrix.
M_GRID = np.concatenate([np.linspace(0.0, 0.99, 34), 1 - np.array([1e-3, 1e-6, 1e-9, 1e-12])])
# Several periods: 4 K(m) is 6.3 at m = 0 and 61 at m = 1 - 1e-12.
U_GRID = np.concatenate(
    [[0.0, 1e-9, 0.3, 1.0, 2.5, -4.0, 7.0, 12.0, -19.0, 33.0, 64.0], np.linspace(-80, 80, 17)]
)
PHI_GRID = np.array([0.0, 1e-9, 0.2, 0.7, 1.2, np.pi / 2 - 1e-9, np.pi / 2, 1.7, 3.0, 4.5, 10.0, -2.2, -7.9])


def ulp(value, ref, scale=None):
    """``|value - ref|`` in units of eps (of ``value``'s dtype) times ``scale`` (default ``|ref|``)."""
    value = np.asarray(value)
    eps = float(np.finfo(value.dtype).eps)
    ref = np.asarray(ref, np.float64)
    scale = np.abs(ref) if scale is None else np.asarray(scale)
    scale = np.maximum(scale, np.finfo(np.float64).tiny)  # exact zeros must come out exactly
    return np.abs(value.astype(np.float64) - ref) / (eps * scale)


@functools.cache
def mp_jacobi(p: float, us: tuple) -> np.ndarray:
    """``(sn, cn, dn, am)`` at ``m = 1 - p`` (exactly) from mpmath, shape (4, len(us))."""
    with mpmath.workdps(30 + max(0, int(-np.log10(p))) if p > 0 else 30):
        m = 1 - mpmath.mpf(p)
        quarter = mpmath.ellipk(m)
        rows = []
        for u in us:
            u = mpmath.mpf(u)
            sn, cn, dn = (mpmath.ellipfun(f, u, m=m) for f in ("sn", "cn", "dn"))
            sn = sn if u != 0 else mpmath.mpf(0)  # mpmath returns -1e-22 for sn(0)
            theta = mpmath.atan2(sn, cn)
            am = theta + 2 * mpmath.pi * mpmath.nint(
                (mpmath.pi * u / (2 * quarter) - theta) / (2 * mpmath.pi)
            )
            rows.append([float(x) for x in (sn, cn, dn, am)])
    return np.array(rows).T


def jacobi_scale(ref, us, m):
    """``|f| + |u df/du|`` for each of (sn, cn, dn, am), from the reference values."""
    sn, cn, dn, _ = ref
    du = np.stack([cn * dn, sn * dn, m * sn * cn, dn])
    return np.abs(ref) + np.abs(us * du)


def mp_derivative(f, x):
    """``df/dx`` at ``x`` by mpmath's (extrapolated, high-precision) finite differences."""
    return float(mpmath.re(mpmath.diff(f, mpmath.mpf(x))))


# ----------------------------------------------------------------------------------------------
# Values: complete integrals


def test_ellipk_matches_scipy():
    m = np.concatenate([M_GRID, [-0.5, -4.0, -1e3]])
    assert np.max(ulp(call("ellipk", m), sc.ellipk(m))) <= 4


def test_ellipkm1_matches_scipy_and_mpmath():
    p = np.concatenate([10.0 ** -np.arange(0, 301, 10.0), [1e-3, 1e-6, 1e-9, 1e-12, 2.3e-308]])
    k = call("ellipkm1", p)
    assert np.max(ulp(k, sc.ellipkm1(p))) <= 4
    with mpmath.workdps(330):
        ref = [float(mpmath.ellipk(1 - mpmath.mpf(x))) for x in p]
    assert np.max(ulp(k, ref)) <= 3
    # The same function as ellipk where 1 - m is exact.
    m = np.array([0.5, 0.9, 1 - 1e-6, 1 - 1e-12])
    np.testing.assert_array_equal(call("ellipkm1", 1 - m), call("ellipk", m))


def test_ellipe_matches_scipy():
    m = np.concatenate([M_GRID, [-0.5, -4.0]])
    assert np.max(ulp(call("ellipe", m), sc.ellipe(m))) <= 4


def test_complete_special_values():
    k, e = call("ellipk", [0.0, 1.0, 1.5]), call("ellipe", [0.0, 1.0, 1.5])
    np.testing.assert_allclose([k[0], e[0]], np.pi / 2, rtol=EPS64)
    assert k[1] == np.inf and e[1] == 1.0
    assert np.isnan(k[2]) and np.isnan(e[2])
    assert call("ellipkm1", [0.0])[0] == np.inf


def test_legendre_relation():
    # E K' + E' K - K K' = pi / 2 with K' = K(1 - m): K and E on both sides of m = 1/2.
    m = np.concatenate([np.linspace(0.01, 0.99, 25), [1e-6, 1 - 1e-6]])
    k, e = call("ellipk", m), call("ellipe", m)
    kc, ec = call("ellipkm1", m), call("ellipe", 1 - m)
    np.testing.assert_allclose(e * kc + ec * k - k * kc, np.pi / 2, rtol=8 * EPS64)


# ----------------------------------------------------------------------------------------------
# Values: incomplete integrals


def test_incomplete_match_scipy():
    phi, m = np.meshgrid(PHI_GRID, np.concatenate([np.linspace(0.0, 0.999, 12), [-0.5, -3.0]]), indexing="ij")
    f, e = call("ellipkinc", phi, m), call("ellipeinc", phi, m)
    assert np.max(ulp(f, sc.ellipkinc(phi, m))) <= 4
    assert np.max(ulp(e, sc.ellipeinc(phi, m))) <= 4


def test_incomplete_large_negative_m_match_mpmath():
    # m << 0 with m sin^2(phi) of order one: E is small against the terms of the form used for
    # 0 <= m <= 1 (at m = -1e18, phi = 1e-8, E = 5.2e-8 from terms of 1e10); also under jit and in d/dm.
    phi, m = (x.ravel() for x in np.meshgrid([1e-8, 1e-4, 0.3, 2.0, -7.0], [-1e18, -1e8, -1e3, -1.0, -1e-6]))
    e, e_eager = (
        call("ellipeinc", phi, m),
        np.array([float(ellipeinc(a, b)) for a, b in zip(phi, m, strict=True)]),
    )
    d_m = call("grad_ellipeinc", phi, m)[1]
    with mpmath.workdps(40):
        e_ref = np.array([float(mpmath.ellipe(a, b)) for a, b in zip(phi, m, strict=True)])
        d_ref = [
            mp_derivative(lambda t, x=x: mpmath.ellipe(mpmath.mpf(x), t), y)
            for x, y in zip(phi, m, strict=True)
        ]
    assert np.max(ulp(e, e_ref)) <= 8
    assert np.max(ulp(e_eager, e_ref)) <= 8
    np.testing.assert_allclose(d_m, np.asarray(d_ref, np.float64), rtol=1e-14)


def test_incomplete_near_separatrix_match_mpmath():
    # scipy's ellipkinc loses ~log10(1/(1-m)) digits at phi = pi/2 here; mpmath is the reference.
    phi, p = np.meshgrid(PHI_GRID[1:], np.array([1e-3, 1e-6, 1e-9, 1e-12]), indexing="ij")
    m = 1 - p
    f, e = call("ellipkinc", phi, m), call("ellipeinc", phi, m)
    with mpmath.workdps(30):
        f_ref = np.vectorize(lambda a, b: float(mpmath.ellipf(a, b)))(phi, m)
        e_ref = np.vectorize(lambda a, b: float(mpmath.ellipe(a, b)))(phi, m)
    assert np.max(ulp(f, f_ref)) <= 4
    assert np.max(ulp(e, e_ref)) <= 4


def test_incomplete_at_m_equal_one():
    phi = np.array([0.3, -1.2, np.pi / 2, 2.0])
    f, e = call("ellipkinc", phi, 1.0), call("ellipeinc", phi, 1.0)
    np.testing.assert_allclose(f[:2], np.arctanh(np.sin(phi[:2])), rtol=4 * EPS64)
    assert f[2] == np.inf and f[3] == np.inf
    np.testing.assert_allclose(e, [np.sin(0.3), -np.sin(1.2), 1.0, 2 - np.sin(2.0)], rtol=2 * EPS64)


def test_incomplete_periodicity():
    phi, m = np.meshgrid(np.linspace(-1.5, 1.5, 7), [0.0, 0.5, 1 - 1e-9], indexing="ij")
    f, e = call("ellipkinc", phi, m), call("ellipeinc", phi, m)
    k, e0 = call("ellipk", m), call("ellipe", m)
    for j in (-2, 1, 3):
        # phi + j pi is rounded: allow eps |phi + j pi| * dF/dphi, with dF/dphi <= 1/cos(1.5) here.
        tol = 4 * EPS64 * (np.abs(phi) + abs(j) * np.pi) / np.cos(1.5)
        assert np.all(np.abs(call("ellipkinc", phi + j * np.pi, m) - (f + 2 * j * k)) <= tol)
        assert np.all(np.abs(call("ellipeinc", phi + j * np.pi, m) - (e + 2 * j * e0)) <= tol)
    # fl(pi/2) is 6e-17 short of pi/2 and dF/dphi = 1/sqrt(1 - m) there: only m <= 1/2 for F.
    np.testing.assert_allclose(call("ellipkinc", np.pi / 2, m[0, :2]), k[0, :2], rtol=2 * EPS64)
    np.testing.assert_allclose(call("ellipeinc", np.pi / 2, m[0]), e0[0], rtol=2 * EPS64)


# ----------------------------------------------------------------------------------------------
# Values: Jacobi elliptic functions


@pytest.mark.parametrize("p", [1.0, 0.75, 0.5, 0.2, 0.05, 1e-3])
def test_ellipj_matches_scipy(p):
    m = 1 - p
    ours = call("ellipj", U_GRID, m)
    theirs = np.array(sc.ellipj(U_GRID, m))
    err = ulp(ours, theirs, jacobi_scale(mp_jacobi(1 - m, tuple(U_GRID)), U_GRID, m))
    # scipy (cephes) is good for sn, cn, am; its dn = cos(phi) / cos(phi_1 - phi) is not (up to ~70 ulp).
    assert np.max(err[[0, 1, 3]]) <= 5, np.max(err, axis=1)
    assert np.max(err[2]) <= 200


@pytest.mark.parametrize("p", [1.0, 0.5, 0.05, 1e-3, 1e-6, 1e-9, 1e-12, 1e-16, 1e-30, 1e-300])
def test_ellipj_m1_matches_mpmath(p):
    # scipy switches to a first-order expansion for m > 1 - 1e-9 and is inaccurate before that.
    ours = call("ellipj_m1", U_GRID, p)
    ref = mp_jacobi(p, tuple(U_GRID))
    err = ulp(ours, ref, jacobi_scale(ref, U_GRID, 1 - p))
    assert np.max(err) <= 4, np.max(err, axis=1)


@pytest.mark.parametrize("p", [1e-6, 1e-9, 1e-12])
def test_ellipj_near_separatrix_matches_mpmath(p):
    m = 1 - p
    ours = call("ellipj", U_GRID, m)
    ref = mp_jacobi(1 - m, tuple(U_GRID))  # 1 - m is exact: the p that the float m stands for
    err = ulp(ours, ref, jacobi_scale(ref, U_GRID, m))
    assert np.max(err) <= 4, np.max(err, axis=1)


def test_ellipj_relative_accuracy_of_small_cn_dn_near_separatrix():
    # m = 1 - 1e-12, u = 5...20: cn ~ dn ~ 2 exp(-u) down to 4e-9, relatively accurate to a few ulp * u.
    p = 1e-12
    us = np.linspace(5.0, 20.0, 7)
    _, cn, dn, _ = call("ellipj_m1", us, p)
    ref = mp_jacobi(p, tuple(us))
    assert np.max(ulp(cn, ref[1]) / us) <= 3
    assert np.max(ulp(dn, ref[2]) / us) <= 3


@pytest.mark.parametrize("p", [0.5 - 1e-12, 0.5, 0.5 + 1e-12, 0.1, 1e-40])
def test_ellipj_across_its_seams_matches_mpmath(p):
    """The Jacobi functions switch formulas at m = 1/2 (ordinary to complementary nome) and, above
    it, at |u| = K/2, 3K/2, ... (direct to quarter-period shifted): on either side of each seam they
    agree with mpmath to a few ulp of the conditioning |f| + |u df/du|."""
    with mpmath.workdps(60):
        quarter = float(mpmath.ellipk(1 - mpmath.mpf(p)))
    seams = quarter * np.array([0.5, 1.5, -2.5, 7.5])
    us = np.concatenate(
        [seams * (1 - 1e-13), seams, seams * (1 + 1e-13), quarter * np.array([1.0, 2.0, -3.0])]
    )
    ours = call("ellipj_m1", us, p)
    ref = mp_jacobi(p, tuple(us))
    err = ulp(ours, ref, jacobi_scale(ref, us, 1 - p))
    assert np.max(err) <= 4, np.max(err, axis=1)


def test_ellipj_special_parameters():
    u = np.linspace(-30, 30, 41)
    sn, cn, dn, am = call("ellipj", u, 0.0)
    # sin and cos by polynomials of the reduced argument (elliptic._sin_cos): within 2 ulp of libm's.
    np.testing.assert_allclose(sn, np.sin(u), rtol=2 * EPS64, atol=0)
    np.testing.assert_allclose(cn, np.cos(u), rtol=2 * EPS64, atol=0)
    np.testing.assert_array_equal(dn, 1.0)
    np.testing.assert_array_equal(am, u)
    sn, cn, dn, am = call("ellipj", u, 1.0)
    np.testing.assert_allclose(sn, np.tanh(u), rtol=3 * EPS64)
    np.testing.assert_allclose(cn, 1 / np.cosh(u), rtol=3 * EPS64)
    np.testing.assert_allclose(dn, 1 / np.cosh(u), rtol=3 * EPS64)
    np.testing.assert_allclose(am, np.arctan(np.sinh(u)), rtol=3 * EPS64)
    # m = 1 is the limit of m -> 1: at 1 - 1e-16 the difference is O(1e-16 sinh(u)^2).
    near = call("ellipj_m1", u[15:26], 1e-16)
    np.testing.assert_allclose(near, call("ellipj", u[15:26], 1.0), rtol=0, atol=1e-13)


def test_ellipj_outside_domain_is_nan():
    assert np.all(np.isnan(call("ellipj", 0.7, [-0.1, 1.1, np.nan])))
    assert np.all(np.isnan(call("ellipj_m1", 0.7, [-1e-3])))


def test_ellipj_identities():
    rng = np.random.default_rng(0)
    u = rng.uniform(-40, 40, 400)
    m = 1 - np.concatenate([rng.uniform(0, 1, 300), 10.0 ** rng.uniform(-15, -1, 100)])
    p = 1 - m  # exact: so that ellipj_m1(u, p) is ellipj(u, m)
    sn, cn, dn, am = call("ellipj_m1", u, p)
    np.testing.assert_array_equal(np.stack([sn, cn, dn, am]), call("ellipj", u, m))
    np.testing.assert_allclose(sn**2 + cn**2, 1, rtol=0, atol=4 * EPS64)
    np.testing.assert_allclose(dn**2 + m * sn**2, 1, rtol=0, atol=4 * EPS64)
    assert np.all(np.abs(np.sin(am) - sn) <= 4 * EPS64 * (1 + np.abs(am)))
    # F(am(u)) = u, up to the rounding of am (eps |am|, magnified by dF/dphi = 1/dn) and of u.
    f_am = call("ellipkinc", am, m)
    assert np.all(np.abs(f_am - u) <= 8 * EPS64 * (np.abs(u) + np.abs(am) / dn))

    k = call("ellipkm1", p)
    # Quarter period: sn(K) = 1, cn(K) = 0, dn(K) = sqrt(p), am(K) = pi/2, up to eps K in the argument.
    sn_k, cn_k, dn_k, am_k = call("ellipj_m1", k, p)
    np.testing.assert_allclose(sn_k, 1, rtol=0, atol=2 * EPS64)
    assert np.all(np.abs(cn_k) <= 4 * EPS64 * k * np.sqrt(p))
    np.testing.assert_allclose(dn_k, np.sqrt(p), rtol=4 * EPS64)
    assert np.all(np.abs(am_k - np.pi / 2) <= 4 * EPS64 * (k * np.sqrt(p) + 1))
    # Period 4K for sn, cn; 2K for dn; am(u + 2K) = am(u) + pi.
    tol = 8 * EPS64 * (np.abs(u) + 4 * k)
    shifted = call("ellipj_m1", u + 4 * k, p)
    assert np.all(np.abs(shifted[:2] - np.stack([sn, cn])) <= tol)
    half = call("ellipj_m1", u + 2 * k, p)
    assert np.all(np.abs(half[0] + sn) <= tol)
    assert np.all(np.abs(half[2] - dn) <= tol)
    assert np.all(np.abs(half[3] - (am + np.pi)) <= tol)
    # Odd / even in u, exactly.
    neg = call("ellipj_m1", -u, p)
    np.testing.assert_array_equal(neg, np.stack([-sn, cn, dn, -am]))


# ----------------------------------------------------------------------------------------------
# Derivatives


def test_complete_integral_derivatives():
    m = np.array([0.0, 1e-8, 0.3, 0.9, 1 - 1e-6, 1 - 1e-12, -2.0])
    dk, de, dkm1 = call("grad_ellipk", m), call("grad_ellipe", m), call("grad_ellipkm1", 1 - m)
    with mpmath.workdps(40):
        dk_ref = [mp_derivative(mpmath.ellipk, x) if x != 0 else np.pi / 8 for x in m]
        de_ref = [mp_derivative(mpmath.ellipe, x) if x != 0 else -np.pi / 8 for x in m]
    np.testing.assert_allclose(dk, dk_ref, rtol=1e-14)
    np.testing.assert_allclose(de, de_ref, rtol=1e-14)
    np.testing.assert_allclose(dkm1, -np.asarray(dk_ref), rtol=1e-14)
    # The closed form at m = 0 and the log singularity at m = 1.
    np.testing.assert_allclose(dk[0], np.pi / 8, rtol=2 * EPS64)
    assert call("grad_ellipk", [1.0])[0] == np.inf
    assert call("grad_ellipe", [1.0])[0] == -np.inf


def test_incomplete_integral_derivatives():
    phi, m = (
        x.ravel()
        for x in np.meshgrid([0.0, 1e-8, 0.4, 1.5, np.pi / 2, 2.0, -4.0, 7.0], [0.0, 0.3, 0.9, 1 - 1e-6])
    )
    with mpmath.workdps(40):
        for name, mp_f in (("ellipkinc", mpmath.ellipf), ("ellipeinc", mpmath.ellipe)):
            rev, fwd = call("grad_" + name, phi, m), call("jac_" + name, phi, m)
            for a, b in zip(rev, fwd, strict=True):
                np.testing.assert_allclose(a, b, rtol=EPS64, atol=0)
            for i, (x, y) in enumerate(zip(phi, m, strict=True)):
                d_phi = mp_derivative(lambda t, y=y, g=mp_f: g(t, mpmath.mpf(y)), x)
                d_m = mp_derivative(lambda t, x=x, g=mp_f: g(mpmath.mpf(x), t), y)
                np.testing.assert_allclose(rev[0][i], d_phi, rtol=1e-14, err_msg=f"{name} phi={x} m={y}")
                np.testing.assert_allclose(rev[1][i], d_m, rtol=1e-14, err_msg=f"{name} phi={x} m={y}")


JAC_POINTS = [(u, m) for m in (0.0, 0.3, 0.8, 1 - 1e-6, 1 - 1e-9) for u in (0.0, 0.3, 1.9, -6.5, 25.0)]


def mp_jacobi_derivatives(u, m):
    """``d/du`` and ``d/dm`` of (sn, cn, dn, am) from mpmath."""

    def am(x, y):
        sn, cn = (mpmath.re(mpmath.ellipfun(f, x, m=y)) for f in ("sn", "cn"))
        theta = mpmath.atan2(sn, cn)
        v = mpmath.pi * x / (2 * mpmath.re(mpmath.ellipk(y)))
        return theta + 2 * mpmath.pi * mpmath.nint((v - theta) / (2 * mpmath.pi))

    fs = [lambda x, y, f=f: mpmath.re(mpmath.ellipfun(f, x, m=y)) for f in ("sn", "cn", "dn")] + [am]
    with mpmath.workdps(40):
        uu, mm = mpmath.mpf(u), mpmath.mpf(m)
        d_u = [mp_derivative(lambda t, f=f: f(t, mm), u) for f in fs]
        d_m = [mp_derivative(lambda t, f=f: f(uu, t), m) for f in fs]
    return d_u, d_m


def test_ellipj_derivatives_match_mpmath():
    u, m = (np.array(x) for x in zip(*JAC_POINTS, strict=True))
    fwd = call("jac_ellipj", u, m)
    ref = [mp_jacobi_derivatives(*pt) for pt in JAC_POINTS]
    d_u_ref = np.array([r[0] for r in ref])
    d_m_ref = np.array([r[1] for r in ref])
    np.testing.assert_allclose(fwd[0], d_u_ref, rtol=0, atol=1e-14)
    # d/dm grows like u / (1 - m): compare relative to max(1, |ref|).
    assert np.max(np.abs(fwd[1] - d_m_ref) / np.maximum(1, np.abs(d_m_ref))) <= 1e-13
    # Reverse mode agrees with forward mode.
    rev = call("jacrev_ellipj", u, m)
    np.testing.assert_allclose(rev[0], fwd[0], rtol=EPS64, atol=0)
    np.testing.assert_allclose(rev[1], fwd[1], rtol=EPS64, atol=0)


def test_ellipj_derivatives_match_finite_differences():
    # Central differences of the function itself (step 1e-6: truncation ~1e-12, rounding ~1e-10).
    rng = np.random.default_rng(1)
    u = rng.uniform(-10, 10, 40)
    m = rng.uniform(0.05, 0.95, 40)
    h = 1e-6
    d_u, d_m = call("jac_ellipj", u, m)
    fd_u = (call("ellipj", u + h, m) - call("ellipj", u - h, m)).T / (2 * h)
    fd_m = (call("ellipj", u, m + h) - call("ellipj", u, m - h)).T / (2 * h)
    np.testing.assert_allclose(d_u, fd_u, rtol=1e-7, atol=1e-8)
    np.testing.assert_allclose(d_m, fd_m, rtol=1e-7, atol=1e-8)


def test_ellipj_m1_derivative_is_minus_d_dm():
    u = np.array([0.4, -3.0, 17.0])
    p = np.array([0.5, 2.0**-20, 2.0**-40])  # 1 - (1 - p) == p
    d_u_p, d_p = call("jac_ellipj_m1", u, p)
    d_u_m, d_m = call("jac_ellipj", u, 1 - p)
    np.testing.assert_array_equal(d_u_p, d_u_m)
    np.testing.assert_allclose(d_p, -d_m, rtol=4 * EPS64)


def test_ellipj_derivatives_at_separatrix():
    # At m = 1 exactly the m-derivative is the first-order term of A&S 16.15 (mpmath just below 1).
    us = np.array([0.0, 0.5, 3.0, -8.0])
    d_m = call("jac_ellipj", us, 1.0)[1]
    with mpmath.workdps(80):
        m = 1 - mpmath.mpf("1e-40")
        ref = [
            [
                mp_derivative(lambda t, f=f, u=u: mpmath.ellipfun(f, mpmath.mpf(u), m=t), m)
                for f in ("sn", "cn", "dn")
            ]
            for u in us
        ]
    np.testing.assert_allclose(d_m[:, :3], ref, rtol=1e-13, atol=1e-15)
    # Finite at and next to both ends of the range, forward and reverse.
    u, m = (x.ravel() for x in np.meshgrid([0.0, 1.0, -20.0], [0.0, 1 - 1e-12, 1.0]))
    for name in ("jac_ellipj", "jacrev_ellipj"):
        assert all(np.all(np.isfinite(d)) for d in call(name, u, m))
    assert all(np.all(np.isfinite(d)) for d in call("jac_ellipj_m1", u, 1 - m))


def test_derivative_in_one_argument_ignores_infinite_other():
    # dF/dm = inf at m = 1 (and d cn/dm overflows at u = 800), but the derivatives in phi or u alone
    # are finite: the m-tangent is a symbolic zero, never inf * 0.
    @jax.jit
    def derivatives(phi, u, m):
        return jax.jacfwd(ellipkinc)(phi, m), jax.jacfwd(_stacked(ellipj))(u, m), jax.grad(ellipeinc)(phi, m)

    d_phi, d_u, d_phi_e = derivatives(jnp.asarray(0.3), jnp.asarray(800.0), jnp.asarray(1.0))
    np.testing.assert_allclose(d_phi, 1 / np.cos(0.3), rtol=2 * EPS64)
    np.testing.assert_allclose(d_phi_e, np.cos(0.3), rtol=2 * EPS64)
    np.testing.assert_array_equal(d_u, [0.0, 0.0, 0.0, 0.0])


def test_second_derivatives():
    hess = jax.jit(jax.hessian(lambda x: jnp.stack(ellipj(x[0], x[1])[:3])))(jnp.asarray([1.0, 0.5]))
    with mpmath.workdps(40):
        for i, f in enumerate(("sn", "cn", "dn")):
            for orders, (a, b) in (((2, 0), (0, 0)), ((1, 1), (0, 1)), ((0, 2), (1, 1))):
                ref = mpmath.diff(lambda s, t, f=f: mpmath.ellipfun(f, s, m=t), (1.0, 0.5), orders)
                np.testing.assert_allclose(hess[i, a, b], float(ref), rtol=1e-13)


# ----------------------------------------------------------------------------------------------
# float32, batching, jit


def test_float32():
    rng = np.random.default_rng(2)
    u = rng.uniform(-20, 20, 256).astype(np.float32)
    p = (10.0 ** rng.uniform(-37, 0, 256)).astype(np.float32)
    phi = rng.uniform(-6, 6, 256).astype(np.float32)
    m = rng.uniform(0, 1, 256).astype(np.float32)

    ours = JIT["ellipj_m1"](jnp.asarray(u), jnp.asarray(p))
    assert ours.dtype == jnp.float32
    ref = call("ellipj_m1", u.astype(np.float64), p.astype(np.float64))
    assert np.max(ulp(np.asarray(ours), ref, jacobi_scale(ref, u, 1 - p.astype(np.float64)))) <= 4

    for name, args in (
        ("ellipk", (m,)),
        ("ellipe", (m,)),
        ("ellipkm1", (p,)),
        ("ellipkinc", (phi, m)),
        ("ellipeinc", (phi, m)),
    ):
        out = JIT[name](*map(jnp.asarray, args))
        assert out.dtype == jnp.float32
        # E(phi) for phi just past pi/2: 2 E(m) + E(phi - pi) cancels one or two bits.
        assert np.max(ulp(out, call(name, *(a.astype(np.float64) for a in args)))) <= 8, name

    d_u, d_m = JIT["jac_ellipj"](jnp.asarray(u[:64]), jnp.asarray(m[:64]))
    assert d_u.dtype == d_m.dtype == jnp.float32
    d_u64, d_m64 = call("jac_ellipj", u[:64].astype(np.float64), m[:64].astype(np.float64))
    np.testing.assert_allclose(d_u, d_u64, rtol=0, atol=1e-5 * np.max(np.abs(u)))
    np.testing.assert_allclose(d_m, d_m64, rtol=1e-3, atol=1e-4 * np.max(np.abs(d_m64)))


@pytest.mark.parametrize("shape", [(), (5,), (2, 3)])
def test_batching_and_jit(shape):
    rng = np.random.default_rng(3)
    u = jnp.asarray(rng.uniform(-10, 10, shape))
    m = jnp.asarray(rng.uniform(0, 1, shape))
    out = jax.jit(ellipj)(u, m)
    assert all(x.shape == shape and x.dtype == jnp.float64 for x in out)
    np.testing.assert_allclose(np.stack(out), call("ellipj", u, m), rtol=2 * EPS64, atol=2 * EPS64)
    for f, args in (
        (ellipk, (m,)),
        (ellipe, (m,)),
        (ellipkm1, (m,)),
        (ellipkinc, (u, m)),
        (ellipeinc, (u, m)),
    ):
        assert jax.eval_shape(f, *args).shape == shape
    if shape:
        flat = jax.jit(jax.vmap(ellipj))(u.reshape(-1), m.reshape(-1))
        np.testing.assert_array_equal(np.stack(flat).reshape((4,) + shape), np.stack(out))


def test_broadcasting():
    u = np.linspace(-3, 3, 6).reshape(2, 3)
    m = np.array([0.1, 0.5, 0.9])
    out = jax.eval_shape(ellipj, jnp.asarray(u), jnp.asarray(m))
    assert all(x.shape == (2, 3) for x in out)
    assert jax.eval_shape(ellipj, jnp.asarray(0.5), jnp.asarray(m))[0].shape == (3,)
    assert jax.eval_shape(ellipkinc, jnp.asarray(u), jnp.asarray(m)).shape == (2, 3)
    # A scalar u against a batch of m: the u-gradient sums over the batch.
    g = jax.grad(lambda a: jnp.sum(ellipj(a, jnp.asarray(m))[0]))(jnp.asarray(0.8))
    _, cn, dn, _ = call("ellipj", 0.8, m)
    np.testing.assert_allclose(g, np.sum(cn * dn), rtol=2 * EPS64)


# --------------------------------------------------------------------------------------------------
# Carlson's R_J

elliprj_at = jax.jit(elliprj)


def test_elliprj_matches_mpmath_and_scipy():
    rng = np.random.default_rng(7)
    x, y, z = rng.uniform(0, 2, (3, 256))
    x[:32] *= 1e-12  # one tiny argument
    x[32:64], y[32:64] = x[32:64] * 1e-9, y[32:64] * 1e-9  # two tiny arguments
    x[64:72] = 0.0
    # p above all of x, y, z (the torque-free orientation's case) and anywhere in (0, 2)
    p = np.where(
        np.arange(256) % 2 == 0,
        np.maximum(np.maximum(x, y), z) * rng.uniform(1, 10, 256),
        rng.uniform(0, 2, 256),
    )
    got = np.asarray(elliprj_at(x, y, z, p))
    with mpmath.workdps(30):
        ref = np.array([float(mpmath.elliprj(*v)) for v in zip(x, y, z, p, strict=True)])
    err = np.abs(got / ref - 1) / EPS64
    assert np.max(err) < 8
    np.testing.assert_allclose(got, sc.elliprj(x, y, z, p), rtol=8 * EPS64)
    # R_J(x, y, z, z) = R_D(x, y, z); R_J(x, x, x, x) = x^(-3/2).
    np.testing.assert_allclose(np.asarray(elliprj_at(x, y, z, z)), sc.elliprd(x, y, z), rtol=8 * EPS64)
    np.testing.assert_allclose(np.asarray(elliprj_at(y, y, y, y)), y**-1.5, rtol=4 * EPS64)


@pytest.mark.parametrize("dtype", [jnp.float64, jnp.float32])
def test_elliprj_with_arguments_decades_apart_against_mpmath(dtype):
    """p far below x, y, z lost digits in R_C(1, 1 + e) as e -> -1 (R_J(1, 2, 3, 1e-100) was 46
    against 141); p far above them outran the fixed duplication steps (R_J(1, 2, 3, 1e9) 37 % off,
    R_J(1, 1, 1, 1e100) 5e-146 against 3e-100) or overflowed to NaN (p >= 1e150)."""
    rng = np.random.default_rng(11)
    eps, decades = (EPS64, 120) if dtype == jnp.float64 else (EPS32, 15)
    args = 10.0 ** rng.uniform(-decades, decades, (4, 64))
    named = [(1, 2, 3, 1e-100), (1, 2, 3, 1e9), (1, 1, 1, 1e100), (1, 1, 1, 1e150), (1e-100, 1e-12, 1, 1)]
    if dtype == jnp.float32:
        named = [(1, 2, 3, 1e-16), (1, 2, 3, 1e9), (1, 1, 1, 1e30), (1e-30, 1e-6, 1, 1)]
    args = np.concatenate([args, np.array(named, np.float64).T], axis=1)
    got = np.asarray(elliprj_at(*(jnp.asarray(a, dtype) for a in args)), np.float64)
    # mpmath's own elliprj needs a working precision beyond the arguments' spread (at 60 digits
    # R_J(4.7e-11, 1, 5.6e-59, 5.8e-193) is 0.24 % off its value at 80).
    with mpmath.workdps(300):
        ref = np.array([float(mpmath.elliprj(*(mpmath.mpf(float(v)) for v in col))) for col in args.T])
    assert np.max(np.abs(got / ref - 1)) < 16 * eps


def test_elliprj_domain_float32_and_gradient():
    nan_cases = np.array(
        [[1.0, 1.0, 1.0, 0.0], [1.0, 1.0, 1.0, -1.0], [-1.0, 1.0, 1.0, 1.0], [0.0, 0.0, 1.0, 1.0]]
    )
    assert np.all(np.isnan(np.asarray(elliprj_at(*nan_cases.T))))
    rng = np.random.default_rng(8)
    args = rng.uniform(0.1, 2, (4, 64)).astype(np.float32)
    out = elliprj_at(*args)
    assert out.dtype == jnp.float32
    ref = sc.elliprj(*args.astype(np.float64))
    assert np.max(np.abs(np.asarray(out, np.float64) / ref - 1)) < 16 * EPS32
    # Gradient (automatic differentiation through the duplication) vs central differences.
    point = np.array([0.3, 1.1, 0.7, 1.9])
    grad = np.asarray(jax.jit(jax.jacfwd(lambda v: elliprj(*v)))(jnp.asarray(point)))
    h = 1e-6
    fd = [(sc.elliprj(*(point + h * e)) - sc.elliprj(*(point - h * e))) / (2 * h) for e in np.eye(4)]
    np.testing.assert_allclose(grad, fd, rtol=1e-8)


@pytest.mark.parametrize("dtype", [jnp.float64, jnp.float32])
def test_precession_rf_against_mpmath_near_and_far_apart(dtype):
    """The precession's unrolled ``R_F`` agrees with mpmath's ``elliprf`` to a few ulp for arguments
    within a decade of each other and for arguments spread over 30 decades (float32) or 300
    (float64), one argument 0 (the separatrix's ``1 - m``) included."""
    from rigidjax._closed_form import precession

    rng = np.random.default_rng(7)
    eps = EPS64 if dtype == jnp.float64 else EPS32
    widest = 300 if dtype == jnp.float64 else 30
    for decades in (1, widest):
        x, y, z = (10 ** rng.uniform(-decades, 0, 200) for _ in range(3))
        if decades > 1:
            x[0] = 0.0
        args = [jnp.asarray(a, dtype) for a in (x, y, z)]
        got = np.asarray(jax.jit(precession._carlson_rf)(*args), np.float64)
        with mpmath.workdps(30):
            ref = [float(mpmath.elliprf(*(float(v) for v in vals))) for vals in zip(*args, strict=True)]
        np.testing.assert_allclose(got, ref, rtol=8 * eps, atol=0)


def test_edges_of_the_domains_against_mpmath():
    """m > 1 in the incomplete integrals gave numbers (F(3.3 | 1.2) = -64014.6, where mpmath's value
    is complex and scipy's NaN); E(m) for m = -1e200 was -inf (m p overflowed); dF/dm at m = 1 was
    inf for |phi| < pi/2 (it is finite: mpmath 0.0250676 at phi = 0.5); the derivative of R_J with
    respect to an argument at 0 was finite (-0.06), where R_J falls like -sqrt(x)."""
    for phi, m in [(0.5, 1.5), (3.3, 1.2), (0.5, 1 + 1e-15)]:
        assert np.isnan(float(ellipkinc(phi, m))) and np.isnan(float(ellipeinc(phi, m)))
    for m in (-1e50, -1e200, -1e300):
        ref = float(mpmath.ellipe(mpmath.mpf(m)))
        np.testing.assert_allclose(float(ellipe(m)), ref, rtol=4 * EPS64)
    np.testing.assert_allclose(float(ellipe(np.float32(-1e30))), float(mpmath.ellipe(-1e30)), rtol=4 * EPS32)
    with mpmath.workdps(40):
        for phi in (0.5, 1.2, -0.7):
            ref = mpmath.diff(lambda m, phi=phi: mpmath.ellipf(phi, m), mpmath.mpf(1) - mpmath.mpf(10) ** -30)
            np.testing.assert_allclose(
                float(jax.grad(ellipkinc, argnums=1)(phi, 1.0)), float(ref), rtol=8 * EPS64
            )
        partials = jax.grad(elliprj, argnums=(0, 1, 2, 3))(0.0, 1.0, 2.0, 3.0)
        assert float(partials[0]) == -np.inf
        for k, value in enumerate(partials[1:], start=1):
            args = [mpmath.mpf(v) for v in (0, 1, 2, 3)]

            def along(h, k=k, args=args):
                shifted = list(args)
                shifted[k] += h
                return mpmath.elliprj(*shifted)

            np.testing.assert_allclose(float(value), float(mpmath.diff(along, 0)), rtol=1e-13)
        # Forward mode: the tangent is linear in the inputs' tangents, so the -inf of the argument
        # at 0 times a zero tangent is NaN, as for jnp.sqrt at 0 (the documented behaviour).
        columns = jax.jacfwd(elliprj, argnums=(0, 1, 2, 3))(0.0, 1.0, 2.0, 3.0)
        assert float(columns[0]) == -np.inf and np.all(np.isnan(np.array(columns[1:], float)))
    assert float(jax.grad(ellipkinc, argnums=1)(-4.0, 1.0)) == -np.inf  # -2 K of a whole turn back
