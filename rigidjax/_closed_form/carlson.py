"""Carlson's symmetric elliptic integrals ``R_F``, ``R_D`` and ``R_J`` by duplication (DLMF 19.36,
Carlson 1995), with fixed iteration counts per dtype so that they work under ``jit``, ``vmap`` and
``grad``; and the argument handling shared by the elliptic functions of :mod:`.elliptic`.
"""

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np
from jax.custom_derivatives import SymbolicZero

from .._checks import common_float, compiled_once
from .._numerics import safe_sqrt
from .._types import Scalar, ScalarOut

# Carlson duplication: the deviations shrink by 4 per step; 11 suffice for R_F(0, 1, 1e-300).
_CARLSON_STEPS = {np.dtype(np.float32): 8, np.dtype(np.float64): 12}
# R_J with p far above x, y, z: each step divides p by 4 while x, y, z barely move, until p meets
# them; arguments scaled to at most 1 are at least the smallest normal number (2^-126, 2^-1022),
# and the step's weight 4^-m stays above it.
_SPREAD_STEPS = {np.dtype(np.float32): 54, np.dtype(np.float64): 500}
# The first step's lambda (arguments scaled to at most 1) below which the fixed steps fall short:
# R_J(1, 2, 3, 1e6) (lambda 1e-5) was 5e-14 off mpmath with them, R_J(1e-100, 1e-12, 1, 1) 3e-9.
_SLOW_LAMBDA = 1e-2


def _broadcast(arrays, names):
    """``jnp.broadcast_arrays`` with a ``ValueError`` that names the arguments."""
    try:
        return jnp.broadcast_arrays(*arrays)
    except ValueError:
        shapes = ", ".join(f"{n} {tuple(jnp.shape(a))}" for n, a in zip(names, arrays, strict=True))
        raise ValueError(f"the arguments must broadcast against each other, got shapes {shapes}.") from None


def _steps(table, dtype) -> int:
    try:
        return table[np.dtype(dtype)]
    except KeyError:
        raise TypeError(f"elliptic functions support float32 and float64, got dtype {dtype}.") from None


# --------------------------------------------------------------------------------------------------
# Building blocks


def _rf_series(dev_x, dev_y, a_f, scale):
    """``R_F`` from the end of its duplication: the mean ``a_f``, the initial deviations
    ``a_f - x``, ``a_f - y`` shrunk by ``scale = 4^-n``, and the truncated series DLMF 19.36.1."""
    X = dev_x * (scale / a_f)
    Y = dev_y * (scale / a_f)
    Z = -(X + Y)
    e2 = X * Y - Z * Z
    e3 = X * Y * Z
    series_f = (
        1
        - e2 / 10
        + e3 / 14
        + e2 * e2 / 24
        - 3 * e2 * e3 / 44
        - 5 * e2**3 / 208
        + 3 * e3 * e3 / 104
        + e2 * e2 * e3 / 16
    )
    rf = series_f / jnp.sqrt(a_f)
    return rf


def _carlson_rf_rd(x, y, z, with_rd=True):
    """Carlson's ``R_F(x, y, z)`` and ``R_D(x, y, z)`` (DLMF 19.16.5, 19.16.6) by duplication.

    Both share the duplication sequence; ``R_D`` is symmetric in ``x, y`` only. Arguments are
    nonnegative with at most one zero (``R_D`` needs ``z > 0``); a zero ``z`` gives ``R_D = inf``.
    The truncated series are DLMF 19.36.1 (to degree 7) and Carlson (1995) eq. 2.21 (degree 5).
    ``with_rd=False`` returns ``(R_F, None)`` and leaves ``R_D``'s sum out of the loop.
    """
    a_f = (x + y + z) / 3
    a_d = (x + y + 3 * z) / 5
    # Carlson (1995): A_n - x_n = (A_0 - x_0) / 4^n exactly, which keeps the deviations accurate.
    fx, fy = a_f - x, a_f - y
    dx, dy = a_d - x, a_d - y

    def step(_, carry):
        # A loop rather than unrolled steps: unrolled, the steps (and their derivatives) are most of
        # the closed forms' compiled programs, and XLA's compile time grows with them.
        x, y, z, a_f, a_d, tail, scale = carry
        sx, sy, sz = safe_sqrt(x), safe_sqrt(y), safe_sqrt(z)
        lam = sx * (sy + sz) + sy * sz
        if with_rd:
            tail = tail + scale / (sz * (z + lam))
            a_d = (a_d + lam) / 4
        x, y, z = (x + lam) / 4, (y + lam) / 4, (z + lam) / 4
        return x, y, z, (a_f + lam) / 4, a_d, tail, scale / 4

    carry = (x, y, z, a_f, a_d, jnp.zeros_like(x), jnp.ones_like(x))
    *_, a_f, a_d, tail, scale = jax.lax.fori_loop(0, _steps(_CARLSON_STEPS, x.dtype), step, carry)

    rf = _rf_series(fx, fy, a_f, scale)
    if not with_rd:
        return rf, None

    X = dx * (scale / a_d)
    Y = dy * (scale / a_d)
    Z = -(X + Y) / 3
    xy, z2 = X * Y, Z * Z
    e2 = xy - 6 * z2
    e3 = (3 * xy - 8 * z2) * Z
    e4 = 3 * (xy - z2) * z2
    e5 = xy * z2 * Z
    series_d = 1 - 3 * e2 / 14 + e3 / 6 + 9 * e2 * e2 / 88 - 3 * e4 / 22 - 9 * e2 * e3 / 52 + 3 * e5 / 26
    rd = scale * series_d / (a_d * jnp.sqrt(a_d)) + 3 * tail
    return rf, rd


def _rd_complete(p):
    """``R_D(0, 1, p) = 6 dK/dm``; ``inf`` at ``p = 0``."""
    return _carlson_rf_rd(jnp.zeros_like(p), jnp.ones_like(p), p)[1]


def _rc_one(e, one_plus_e):
    """``R_C(1, 1 + e)`` for ``e > -1``: ``atan(sqrt e) / sqrt e`` (``e > 0``), ``atanh(sqrt(-e)) /
    sqrt(-e)`` (``e < 0``) and a Taylor series for ``|e| < 1/64`` (relative error < 1e-17).

    ``one_plus_e`` is ``1 + e`` formed by the caller without cancellation: as ``e -> -1`` (``R_J``
    with ``p`` far below ``x, y, z``) ``atanh(u) = log1p(u) - log(1 - u^2) / 2`` reads it there."""
    small = jnp.abs(e) < 1 / 64
    positive = e > 0
    e_pos = jnp.where(positive & ~small, e, jnp.ones_like(e))
    neg = ~positive & ~small
    e_neg = jnp.where(neg, -e, jnp.full_like(e, 0.5))
    r_pos = jnp.arctan(jnp.sqrt(e_pos)) / jnp.sqrt(e_pos)
    u = jnp.sqrt(e_neg)
    r_neg = (jnp.log1p(u) - 0.5 * jnp.log(jnp.where(neg, one_plus_e, 0.75))) / u
    e_small = jnp.where(small, e, jnp.zeros_like(e))
    series = jnp.zeros_like(e)
    for k in range(10, -1, -1):  # sum_k (-e)^k / (2k + 1)
        series = series * (-e_small) + 1.0 / (2 * k + 1)
    return jnp.where(small, series, jnp.where(positive, r_pos, r_neg))


def _carlson_rf_rj(x, y, z, p, spread_steps=False):
    """Carlson's ``R_F(x, y, z)`` and ``R_J(x, y, z, p)`` (DLMF 19.16.1-2) by duplication (Carlson 1995).

    Both share the duplication of ``x, y, z``. ``x, y, z >= 0`` with at most one zero and ``p > 0``
    (no Cauchy principal value). Differentiable by automatic differentiation through the fixed number
    of steps, finite where every argument is positive.
    """
    a_f = (x + y + z) / 3
    a_j = (x + y + z + 2 * p) / 5
    gaps = (p - x, p - y, p - z)  # delta = their product; each shrinks by 4 per step, exactly
    dev_f = (a_f - x, a_f - y)
    dev_j = (a_j - x, a_j - y, a_j - z)

    def step(_, carry):
        # A loop rather than unrolled steps: R_C's atan/atanh per step made the unrolled form slow to
        # compile (seconds on CPU).
        x, y, z, p, a_f, a_j, total, scale = carry
        sx, sy, sz, sp = safe_sqrt(x), safe_sqrt(y), safe_sqrt(z), safe_sqrt(p)
        lam = sx * (sy + sz) + sy * sz
        # 1 + e = (d^2 + delta_m) / d^2 with delta_m = (s^2 - a^2)(s^2 - b^2)(s^2 - c^2) = d (s - a)(s - b)
        # (s - c), s = sqrt p, a = sqrt x, ...: = 2 s (p + lam) / d, a sum of positive terms.
        # Here and below in ratios of size O(1): d ~ A^(3/2), d^2 and delta 4^(-3m) underflow where
        # the arguments meet at a tiny value A (R_J(1e-300, 1e-300, 1e-300, 1)).
        pair = (sp + sx) * (sp + sy)
        one_plus_e = 2 * (sp / (sp + sx)) * ((p + lam) / ((sp + sy) * (sp + sz)))
        e = math.prod(g * scale / (sp + sk) ** 2 for g, sk in zip(gaps, (sx, sy, sz), strict=True))
        total = total + _rc_one(e, one_plus_e) * (scale / pair) / (sp + sz)
        x, y, z, p = (x + lam) / 4, (y + lam) / 4, (z + lam) / 4, (p + lam) / 4
        return x, y, z, p, (a_f + lam) / 4, (a_j + lam) / 4, total, scale / 4

    carry = (x, y, z, p, a_f, a_j, jnp.zeros_like(x), jnp.ones_like(x))
    steps = _steps(_CARLSON_STEPS, x.dtype) + (_steps(_SPREAD_STEPS, x.dtype) if spread_steps else 0)
    *_, a_f, a_j, total, scale = jax.lax.fori_loop(0, steps, step, carry)

    rf = _rf_series(dev_f[0], dev_f[1], a_f, scale)

    X, Y, Z = (dev * (scale / a_j) for dev in dev_j)
    P = -(X + Y + Z) / 2
    e2 = X * Y + X * Z + Y * Z - 3 * P * P
    xyz = X * Y * Z
    e3 = xyz + 2 * e2 * P + 4 * P**3
    e4 = (2 * xyz + e2 * P + 3 * P**3) * P
    e5 = xyz * P * P
    series = 1 - 3 * e2 / 14 + e3 / 6 + 9 * e2 * e2 / 88 - 3 * e4 / 22 - 9 * e2 * e3 / 52 + 3 * e5 / 26
    return rf, (scale / a_j) * series / jnp.sqrt(a_j) + 6 * total


def elliprj(x: Scalar, y: Scalar, z: Scalar, p: Scalar) -> ScalarOut:
    """Carlson's symmetric integral of the third kind, as ``scipy.special.elliprj`` (real arguments).

    ``R_J(x, y, z, p) = 3/2 int_0^inf dt / ((t + p) sqrt((t + x) (t + y) (t + z)))``. Gradients by
    automatic differentiation through the duplication, finite wherever all arguments are positive;
    ``-inf`` with respect to an argument at 0. Reverse mode (``jax.grad``) then gives the other
    arguments' finite partials; forward mode (``jax.jvp``, ``jax.jacfwd``) gives NaN in every
    direction, as for ``jnp.sqrt`` at 0: the tangent is linear in the inputs' tangents, and the
    ``-inf`` times a zero tangent is NaN.
    Within a few ulp of mpmath (at 300 digits) for arguments spread over 240 decades (float32: 30);
    5e-14 at 280 decades, 2e-9 at 300. Where one argument lies far from the others (the first
    duplication step's ``lambda`` below 1e-2 of the largest), the batch runs the duplication over
    the dtype's whole range: about 40 times the cost, paid only then.

    **Arguments:**

    - `x`, `y`, `z`, `p`: ``x, y, z >= 0`` (at most one of them zero) and ``p > 0`` (the principal
      value for ``p < 0`` is not implemented); all four broadcast against each other.

    **Returns:** ``R_J``; NaN outside the domain above or for NaN input.
    """
    x, y, z, p = common_float(x, y, z, p, names=["x", "y", "z", "p"])
    x, y, z, p = _broadcast((x, y, z, p), ("x", "y", "z", "p"))
    return compiled_once(_elliprj)(x, y, z, p)


@jax.custom_jvp
def _elliprj(x, y, z, p):
    return _elliprj_values(x, y, z, p)


@functools.partial(_elliprj.defjvp, symbolic_zeros=True)
def _elliprj_jvp(primals, tangents):
    """The derivatives through the duplication, except with respect to an argument at 0, where
    ``R_J`` falls like ``-sqrt(x)`` and the derivative is ``-inf`` (through the duplication it came
    out finite and wrong: -0.06 for ``R_J(0, 1, 2, 3)``)."""
    dense = tuple(
        jnp.zeros_like(v) if isinstance(t, SymbolicZero) else t
        for v, t in zip(primals, tangents, strict=True)
    )
    value, slope = jax.jvp(_elliprj_values, primals, dense)
    for v, t in zip(primals[:3], tangents[:3], strict=True):
        if not isinstance(t, SymbolicZero):  # a zero tangent would make -inf * 0 a NaN
            slope = slope + jnp.where(v == 0, -jnp.inf, 0.0) * t
    return value, slope


def _elliprj_values(x, y, z, p):
    zeros = (x == 0).astype(jnp.int32) + (y == 0).astype(jnp.int32) + (z == 0).astype(jnp.int32)
    bad = (x < 0) | (y < 0) | (z < 0) | (p <= 0) | (zeros > 1) | jnp.isnan(x + y + z + p)
    one = jnp.ones_like(x)
    x, y, z, p = (jnp.where(bad, one, v) for v in (x, y, z, p))
    # R_J is homogeneous of degree -3/2: arguments scaled to at most 1, so that the products of the
    # duplication (delta, d^2) neither overflow nor underflow.
    largest = jnp.maximum(jnp.maximum(x, y), jnp.maximum(z, p))
    scaled = (x / largest, y / largest, z / largest, p / largest)
    # p far above x, y, z: each duplication step divides p by 4 while x, y, z hardly move (their
    # lambda stays small), so the fixed steps end before the arguments meet (R_J(1, 2, 3, 1e9) was
    # 37 % off). Where the first step's lambda is that small, the batch runs the steps that cover
    # the dtype's range: about 40 times the cost, paid only then.
    sx, sy, sz = (jnp.sqrt(v) for v in scaled[:3])
    slow = jnp.any(sx * (sy + sz) + sy * sz < _SLOW_LAMBDA)
    value = jax.lax.cond(
        slow,
        lambda *a: _carlson_rf_rj(*a, spread_steps=True)[1],
        lambda *a: _carlson_rf_rj(*a)[1],
        *scaled,
    )
    return jnp.where(bad, jnp.nan, value / largest / jnp.sqrt(largest))
