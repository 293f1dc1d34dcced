"""The Jacobi elliptic functions' theta series (:func:`.elliptic.ellipj`), the AGM, and the
``sin``/``cos`` and ``tanh``/``sech`` pairs they are built from, in pure JAX."""

import jax
import jax.numpy as jnp
import numpy as np

from .barrier import _materialised
from .carlson import _steps

# Iteration counts, checked against mpmath for p = 1 - m down to 1e-300 (float64) / 1e-38 (float32).
# AGM(1, sqrt(p)): the ratio b/a goes 1e-150 -> 2e-75 -> ... -> 1 - 4e-25 in 12 steps.
_AGM_STEPS = {np.dtype(np.float32): 9, np.dtype(np.float64): 13}
# AGM(1, sqrt(b)) for b >= 1/2: the relative gap 0.29 -> 1e-2 -> 1.4e-5 -> 2.4e-11 -> 7e-23.
_AGM_STEPS_HALF = {np.dtype(np.float32): 4, np.dtype(np.float64): 5}


def _mod(k, n: int):
    """``k mod n`` (``jnp.mod``'s sign) for integer-valued floats ``k`` and a power of two ``n``: exact
    (``k / n`` and its floor are), and vectorised: XLA's remainder is a call per element on CPU."""
    return k - n * jnp.floor(k / n)


def _agm(root, steps=_AGM_STEPS):
    """``AGM(1, root)`` after the number of steps that ``steps`` gives for ``root``'s dtype."""
    a, b = jnp.ones_like(root), root
    for _ in range(_steps(steps, root.dtype)):
        a, b = 0.5 * (a + b), jnp.sqrt(a * b)
    return a


def _nome_parts(m, p):
    """Per body: which side of ``m = 1/2``, ``AGM(1, sqrt(b))`` of the larger of ``b = m, p``, and the
    nome ``q`` of the smaller (``q = exp(-pi K'/K)`` for ``m <= 1/2``, ``q' = exp(-pi K/K')`` above),
    with ``L = -log q'``.

    The nome comes from its series in ``lambda = (1 - b^(1/4)) / (2 (1 + b^(1/4)))`` (DLMF 22.2.2,
    Whittaker & Watson 21.71): ``q = lambda + 2 lambda^5 + 15 lambda^9 + 150 lambda^13 + 1707 lambda^17``,
    exact to rounding for ``lambda <= 0.0432`` (``b >= 1/2``). ``1 - b^(1/4)`` is formed as
    ``(1 - b) / ((1 + sqrt b)(1 + b^(1/4)))``, so the nome keeps its relative accuracy for a ``1 - b``
    down to the smallest normal number, where ``K`` grows like ``log(4 / sqrt(1 - b))``.
    """
    upper = upper_side(m)
    big = jnp.where(upper, m, p)
    small = jnp.where(upper, p, m)
    root = jnp.sqrt(big)
    quarter = jnp.sqrt(root)
    agm = _agm(root, _AGM_STEPS_HALF)
    lam = 0.5 * small / ((1 + root) * (1 + quarter) ** 2)
    l4 = lam**4
    excess = l4 * (2 + l4 * (15 + l4 * (150 + l4 * 1707)))
    nome = lam * (1 + excess)
    positive = lam > 0
    log_nome = jnp.where(positive, jnp.log(jnp.where(positive, lam, 1.0)) + jnp.log1p(excess), -jnp.inf)
    return upper, agm, nome, -log_nome


def upper_side(m):
    """Which side of ``m = 1/2`` each ``m`` lies on (True: above): the rule every branch between the
    two sides' series follows."""
    return m > 0.5


def _guarded(coefficient, x):
    """``coefficient * x`` where a power of the nome that underflows to 0 meets an ``x`` that
    overflows: the power reaches 0 long before ``x`` reaches inf, and the term is then 0."""
    return jnp.where(coefficient == 0, jnp.zeros_like(x), coefficient * x)


def _jacobi_values(u, m, p):
    """``(sn, cn, dn, am)`` for ``0 <= m <= 1``, ``p = 1 - m``, from theta series in a nome of at most
    ``exp(-pi)`` (DLMF 22.2.4-6, 20.2.1-4): three or four terms reach double precision
    (``q^12 < 5e-17``). What depends on ``m`` only (the nome, the quarter period, the values of the
    theta functions at 0: :func:`_jacobi_parameters`) is computed once per ``m`` (``m``, ``p`` of
    fewer axes than ``u``: once per body, not per ``u``) and held in memory before the series.

    - ``m <= 1/2``: the theta functions of ``z = pi u / (2 K)`` and the ordinary nome.
    - ``m > 1/2``: Jacobi's imaginary transformation (DLMF 22.6.20, ``sn(u|m) = -i sc(iu|1-m)``), the
      complementary nome ``q' = exp(-L)`` and the hyperbolic functions of ``y = pi t / (2 K')``. ``u``
      is reduced to ``r`` in ``[-K, K]`` (``sn``, ``cn`` change sign with each half period ``2K``);
      where ``|r| > K/2`` the functions are evaluated at ``t = K - |r|`` and shifted by a quarter
      period (DLMF 22.4.3: ``sn = cd``, ``cn = k' sd``, ``dn = k' nd``). So ``y <= L/4`` (no overflow
      up to ``m = 1 - 1e-300``), and ``cn``, ``dn`` keep their relative accuracy where they are tiny,
      near ``u = K`` close to the separatrix. At ``m = 1`` (``q' = 0``, ``K = inf``) this is
      ``(tanh u, sech u, sech u)``.

    Both sides share one set of series: the odd harmonics ``sin((2n+1) z) / sin z``,
    ``cos((2n+1) z) / cos z`` and the even ones ``cos(2 n z)`` are the same polynomials in ``cos(z)^2``
    as their hyperbolic counterparts in ``cosh(y)^2``. ``theta_1``, ``theta_2`` are divided by their
    common ``2 q^(1/4)`` and written as ``sin z``, ``cos z`` times those polynomials, so ``sn`` and ``cn``
    keep their relative accuracy at their zeros.
    """
    upper = upper_side(m)
    body = _jacobi_parameters(m, p)
    agm, q, half, period, k_prime = body["agm"], body["q"], body["half"], body["period"], body["k_prime"]
    # m > 1/2: the reduction to a quarter period (K = L K' / pi)
    reduce = upper & (period > 0)
    turns = jnp.where(reduce, jnp.round(u / jnp.where(reduce, period, 1.0)), jnp.zeros_like(u))
    r = jnp.where(reduce, u - period * turns, u)
    flip = 1 - 2 * _mod(turns, 2)
    a = jnp.abs(r)
    near = a <= half / 2
    y = jnp.where(near, a, half - a) * agm
    tanh, sech = _tanh_sech(y)  # 2 ulp; XLA's sinh and cosh are off by up to 9 ulp
    sin_z, cos_z = _sin_cos(u * agm)
    odd_sin = jnp.where(upper, tanh, sin_z)
    odd_cos = jnp.where(upper, sech, cos_z)
    c2 = jnp.where(upper, 1 / (odd_cos * odd_cos), odd_cos * odd_cos)  # cosh(y)^2 | cos(z)^2
    q2, q6, q12 = body["q2"], body["q6"], body["q12"]
    odd_s = 1 - _guarded(q2, 4 * c2 - 1) + _guarded(q6, (16 * c2 - 12) * c2 + 1)
    odd_s = odd_s - _guarded(q12, ((64 * c2 - 80) * c2 + 24) * c2 - 1)
    odd_c = 1 + _guarded(q2, 4 * c2 - 3) + _guarded(q6, (16 * c2 - 20) * c2 + 5)
    odd_c = odd_c + _guarded(q12, ((64 * c2 - 112) * c2 + 56) * c2 - 7)
    cos2 = jnp.where(upper, 2 * c2 - 1, 1 - 2 * odd_sin * odd_sin)
    cos4 = 2 * cos2 * cos2 - 1
    cos6 = 2 * cos2 * cos4 - cos2
    e1, e2, e3 = _guarded(q, cos2), _guarded(body["q4"], cos4), _guarded(body["q9"], cos6)
    even3 = 1 + 2 * (e1 + e2 + e3)
    even4 = 1 + 2 * (-e1 + e2 - e3)
    # m <= 1/2: sn = th3 th1 / (th2 th4), cn = th4 th2 / (th2 th4), dn = th4 th3 / (th3 th4) at z and 0;
    # m > 1/2: the same with the roles of theta_2 and theta_4 exchanged (sc, nc, dc of 1 - m).
    den = jnp.where(upper, odd_c, even4)
    sn = body["sn0"] * odd_sin * odd_s / den
    cn = jnp.where(upper, body["cn0"] * even4, body["cn0"] * odd_c) * odd_cos / den
    dn = jnp.where(upper, body["dn0"] * odd_cos, body["dn0"]) * even3 / den
    # Held in memory: each of the results below is computed in a kernel of its own, which would
    # evaluate the series again.
    sn, cn, dn = _materialised((sn, cn, dn))
    shift = upper & ~near
    sn, cn, dn = (
        jnp.where(shift, cn / dn, sn),
        jnp.where(shift, k_prime * sn / dn, cn),
        jnp.where(shift, k_prime / dn, dn),
    )
    sign = jnp.where(upper, flip, jnp.ones_like(flip))
    # sn^2 + cn^2 = 1 to rounding (each is within ~1.5 ulp; the sum of squares would be ~5 ulp off).
    # At q = 0 (m = 0: sin, cos; m = 1: tanh, sech) the values are those functions as they are.
    norm = jnp.where(q > 0, jnp.hypot(sn, cn), jnp.ones_like(sn))
    sn = sign * jnp.where(upper, jnp.sign(r), jnp.ones_like(r)) * sn / norm
    cn = sign * cn / norm
    # am - v is periodic and |am - v| < pi/2 with v = pi u / (2 K): unwrap atan2 about v.
    v = u * body["v_scale"]
    theta = jnp.arctan2(sn, cn)
    am = theta + (2 * jnp.pi) * jnp.round((v - theta) / (2 * jnp.pi))
    return sn, cn, dn, am


def _jacobi_parameters(m, p):
    """What :func:`_jacobi_values` needs of ``m`` alone: the nome and its powers, the AGM, the quarter
    period ``half`` (``K``, ``inf`` at ``m = 1``) and the period ``2K`` of the reduction (0 where
    there is none: ``m <= 1/2``, ``m = 1``), the theta functions' ratios at 0 by which ``sn``, ``cn``,
    ``dn`` are scaled, ``k' = sqrt(p)`` and the rate ``pi / (2 K)`` of ``v``.

    Held in memory (:func:`.barrier._materialised`): fused into the series, which reads them
    broadcast against ``u``, they would be recomputed for every ``u``.
    """
    upper, agm, q, big_l = _nome_parts(m, p)
    half = jnp.where(upper, big_l, jnp.pi) / (2 * agm)
    period = jnp.where(upper & jnp.isfinite(half), 2 * half, 0.0)
    q2 = q * q
    q4 = q2 * q2
    q6, q9, q12 = q4 * q2, q4 * q4 * q, q4 * q4 * q4
    odd_c0 = 1 + q2 + q6 + q12
    even3_0 = 1 + 2 * (q + q4 + q9)
    even4_0 = 1 + 2 * (-q + q4 - q9)
    body = dict(
        agm=agm,
        q=q,
        q2=q2,
        q4=q4,
        q6=q6,
        q9=q9,
        q12=q12,
        half=half,
        period=period,
        sn0=even3_0 / jnp.where(upper, even4_0, odd_c0),
        cn0=jnp.where(upper, odd_c0 / even4_0, even4_0 / odd_c0),
        dn0=jnp.where(upper, odd_c0, even4_0) / even3_0,
        k_prime=jnp.sqrt(p),
        v_scale=jnp.where(upper, jnp.pi * agm / jnp.where(upper, big_l, 1.0), agm),
    )
    names = sorted(body)
    return dict(zip(names, _materialised(tuple(body[k] for k in names)), strict=True))


# pi/2 in three parts (fdlibm's pio2_1, pio2_2, pio2_2t): the first two have 33 significant bits, so
# k times them is exact for |k| < 2^20.
_HALF_PI_PARTS = (1.57079632673412561417e00, 6.07710050630396597660e-11, 2.02226624879595063154e-21)
# fdlibm's kernels: sin r = r + r^3 S(r^2), cos r = 1 - r^2/2 + r^4 C(r^2) on |r| <= pi/4 (< 1 ulp).
_SIN_KERNEL = (
    -1.66666666666666324348e-01,
    8.33333333332248946124e-03,
    -1.98412698298579493134e-04,
    2.75573137070700676789e-06,
    -2.50507602534068634195e-08,
    1.58969099521155010221e-10,
)
_COS_KERNEL = (
    4.16666666666666019037e-02,
    -1.38888888888741095749e-03,
    2.48015872894767294178e-05,
    -2.75573143513906633035e-07,
    2.08757232129817482790e-09,
    -1.13596475577881948265e-11,
)


def _half_pi_parts(dtype) -> tuple[float, float, float]:
    """``pi/2`` in three parts for ``dtype``: the float64 split, or for float32 two parts of 12 bits
    (``k`` times them exact for ``|k| < 2^12``) and the rest."""
    if np.dtype(dtype) == np.float64:
        return _HALF_PI_PARTS
    first = float(np.ldexp(np.floor(np.ldexp(_HALF_PI_PARTS[0], 11)), -11))
    rest = (_HALF_PI_PARTS[0] - first) + _HALF_PI_PARTS[1]
    second = float(np.ldexp(np.floor(np.ldexp(rest, 23)), -23))
    return first, second, float(np.float32((rest - second) + _HALF_PI_PARTS[2]))


@jax.custom_jvp
def _sin_cos(x):
    """``(sin x, cos x)`` from polynomials: within 2 ulp for ``|x| < 2^20 pi/2`` (float32: ``2^12 pi/2``),
    beyond that within a few ulp of ``x`` (the conditioning).

    XLA's ``sin`` and ``cos`` are calls per element on CPU (about three times the cost of this pair,
    which vectorizes). ``x = k pi/2 + r`` (Cody & Waite, three parts), fdlibm's kernels on ``r``, and
    the quadrant ``k mod 4`` exchanges and negates them.
    """
    hi, mid, lo = _half_pi_parts(x.dtype)
    k = jnp.round(x * (2 / np.pi))
    r = ((x - k * hi) - k * mid) - k * lo
    z = r * r
    sin_poly, cos_poly = _SIN_KERNEL[-1], _COS_KERNEL[-1]
    for a, b in zip(_SIN_KERNEL[-2::-1], _COS_KERNEL[-2::-1], strict=True):
        sin_poly, cos_poly = sin_poly * z + a, cos_poly * z + b
    s = r + r * z * sin_poly
    c = 1 - (0.5 * z - z * z * cos_poly)
    quadrant = _mod(k, 4)
    odd = (quadrant == 1) | (quadrant == 3)
    s, c = jnp.where(odd, c, s), jnp.where(odd, s, c)
    return jnp.where(quadrant >= 2, -s, s), jnp.where((quadrant == 1) | (quadrant == 2), -c, c)


@_sin_cos.defjvp
def _sin_cos_jvp(primals, tangents):
    (x,), (x_dot,) = primals, tangents
    s, c = _sin_cos(x)
    return (s, c), (c * x_dot, -s * x_dot)


def _tanh_sech(u):
    """``tanh(u)`` and ``sech(u)`` to ~2 ulp from ``exp`` and ``expm1``.

    XLA's own ``tanh`` and ``1 / cosh`` are off by up to 4 and 9 ulp on CPU.
    """
    e1 = jnp.expm1(-2 * jnp.abs(u))
    e = jnp.exp(-jnp.abs(u))
    return -jnp.sign(u) * e1 / (2 + e1), 2 * e / (1 + e * e)
