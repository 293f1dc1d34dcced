"""Complete and incomplete elliptic integrals and the Jacobi elliptic functions, in pure JAX.

Conventions follow ``scipy.special``: the *parameter* ``m = k**2`` (not the modulus ``k``), so

    K(m) = F(pi/2 | m),   F(phi | m) = int_0^phi dt / sqrt(1 - m sin(t)**2),
    E(m) = E(pi/2 | m),   E(phi | m) = int_0^phi sqrt(1 - m sin(t)**2) dt,

and ``sn(u | m) = sin(am(u | m))`` with ``am`` the inverse of ``F(. | m)``. The ``*m1`` variants take
the complementary parameter ``p = 1 - m`` instead of ``m``, for arguments so close to the separatrix
``m = 1`` that ``1 - m`` cannot be formed in floating point.

Every function is elementwise: the arguments broadcast against each other, float32 stays float32, and
the algorithms use fixed iteration counts (no data-dependent loops), so all of them work under
``jit``, ``vmap`` and ``grad``. The counts are chosen per dtype so that the iterations have converged
for every ``p = 1 - m`` down to the smallest normal number.

Algorithms:

- ``ellipk``, ``ellipkm1``: the arithmetic-geometric mean, ``K = pi / (2 AGM(1, sqrt(p)))``.
- ``ellipj``, ``ellipj_m1``: theta series (DLMF 22.2) in a nome of at most ``exp(-pi)``: the ordinary
  nome for ``m <= 1/2``, the complementary one (Jacobi's imaginary transformation) above, so three
  or four terms reach double precision and each ``u`` costs a ``sin``/``cos`` and an
  ``exp``/``expm1`` pair (both sides are evaluated, then one is selected; ``sin``/``cos`` by fdlibm's
  polynomials, which vectorize). The nome comes from its
  series in the modulus (no second AGM), the argument is reduced to a quarter period, and near
  ``u = K`` the functions are shifted by a quarter period, so ``cn`` and ``dn`` keep their *relative*
  accuracy near ``m = 1`` (where both are tiny, ``~ sech(u)``), unlike the angle recurrence of
  Abramowitz & Stegun 16.4 / cephes.
- ``ellipe``, ``ellipkinc``, ``ellipeinc``: Carlson's symmetric integrals ``R_F`` and ``R_D`` by
  duplication (DLMF 19.36), combined so that every term is positive for ``0 <= m <= 1`` (one of the
  forms of DLMF 19.25(ii)): no cancellation near ``m = 1``, where ``F`` diverges but ``E`` is finite.
- ``elliprj``: Carlson's ``R_J`` by the same duplication (Carlson 1995), in :mod:`.carlson` with
  the other symmetric integrals.

Derivatives are closed forms (``jax.custom_jvp``), exact up to rounding, in every argument:
``dF/dm = sin(phi)**3 R_D(cos(phi)**2, 1, dn**2) / 6`` (DLMF 19.18.1), ``dK/dm = R_D(0, 1, p) / 6``,
``dE(phi|m)/dm = (E - F) / (2 m)`` written without the division, and for the Jacobi functions
``d am/du = dn``, ``d am/dm = -dn dF/dm`` evaluated at ``phi = am``. They stay finite at ``m = 0``;
at ``m = 1`` the Jacobi functions use the limits of Abramowitz & Stegun 16.15.

Bad input: complex and boolean arguments raise ``TypeError``, and arguments that do not broadcast
raise ``ValueError`` naming them, while tracing; half precision (float16, bfloat16) is computed in
float32, as ``scipy.special`` does. Values follow
``scipy.special`` (these are elementwise special functions, used inside rigidjax's closed forms):
NaN in gives NaN out, and an argument outside the domain (e.g. ``m > 1``) gives NaN, documented per
function; nothing raises at run time, so a batch with one bad element keeps its other results.
"""

import functools
import operator

import jax
import jax.numpy as jnp
import numpy as np
from jax.custom_derivatives import SymbolicZero

from .._checks import common_float, compiled_once
from .._types import Scalar, ScalarOut
from .carlson import (
    _broadcast,
    _carlson_rf_rd,
    _rd_complete,
)
from .jacobi import _agm, _jacobi_values, _tanh_sech
from .jacobi import _nome_parts as _nome_parts
from .jacobi import _sin_cos as _sin_cos


def _is_zero(tangent) -> bool:
    return isinstance(tangent, SymbolicZero)


def _linear(terms, like):
    """``sum(coefficient * tangent)`` over the ``(coefficient, tangent)`` pairs, skipping symbolic zeros.

    Skipping them matters where a coefficient is infinite (``dK/dm`` at ``m = 1``): ``inf * 0`` would
    make a derivative with respect to another argument NaN.
    """
    terms = [c * t for c, t in terms if not _is_zero(t)]
    return functools.reduce(operator.add, terms) if terms else jnp.zeros_like(like)


def _as_pair(m_or_p, name: str, complementary: bool):
    """Returns ``(m, p)`` with ``p = 1 - m``, each formed from whichever one the caller gave."""
    (x,) = common_float(m_or_p, names=[name])
    return (1 - x, x) if complementary else (x, 1 - x)


# --------------------------------------------------------------------------------------------------
# Complete integrals


@jax.custom_jvp
def _ellipk(m, p):
    """``K(m)`` from the AGM. ``m`` only enters the derivative; the value uses ``p = 1 - m``."""
    del m
    value = (jnp.pi / 2) / _agm(jnp.sqrt(p))
    return jnp.where(p == 0, jnp.inf, value)


@_ellipk.defjvp
def _ellipk_jvp(primals, tangents):
    # The tangent of p is ignored: p = 1 - m is a function of m, whose tangent is the one used.
    m, p = primals
    m_dot, _ = tangents
    return _ellipk(m, p), _rd_complete(p) / 6 * m_dot


def ellipk(m: Scalar) -> ScalarOut:
    """Complete elliptic integral of the first kind ``K(m)``, as ``scipy.special.ellipk``.

    A float ``m`` cannot lie closer to 1 than ``eps / 2``; below that use ``ellipkm1(p)`` with
    ``p = 1 - m``. The derivative is ``dK/dm = R_D(0, 1, 1 - m) / 6`` (``pi/8`` at ``m = 0``).

    **Arguments:**

    - `m`: the parameter ``m = k**2 <= 1`` (not the modulus ``k``), float32 or float64.

    **Returns:** ``K(m)``, shaped as `m`: ``inf`` at ``m = 1``, NaN for ``m > 1`` or NaN input.
    """
    m, p = _as_pair(m, "m", complementary=False)
    return compiled_once(_ellipk)(m, p)


def ellipkm1(p: Scalar) -> ScalarOut:
    """``K(1 - p)`` of the complementary parameter ``p = 1 - m``, as ``scipy.special.ellipkm1``.

    Accurate for every ``p`` down to the smallest normal number (``K ~ log(4 / sqrt(p))``), also where
    ``m = 1 - p`` would round to 1. The derivative is ``dK/dp = -R_D(0, 1, p) / 6``.

    **Arguments:**

    - `p`: the complementary parameter ``p = 1 - m >= 0``, float32 or float64.

    **Returns:** ``K(1 - p)``, shaped as `p`: ``inf`` at ``p = 0``, NaN for ``p < 0`` or NaN input.
    """
    m, p = _as_pair(p, "p", complementary=True)
    return compiled_once(_ellipk)(m, p)


@jax.custom_jvp
def _ellipe(m, p):
    safe = p > 0
    p_safe = jnp.where(safe, p, jnp.ones_like(p))
    one = jnp.ones_like(p)
    rf, rd = _carlson_rf_rd(
        jnp.zeros((2,) + p.shape, p.dtype), jnp.stack([one, p_safe]), jnp.stack([p_safe, one])
    )
    # The forms of _legendre_values at phi = pi/2, each with terms >= 0: E = p K + (m p / 3)
    # R_D(0, 1, p) for 0 <= m <= 1, and E = K - (m / 3) R_D(0, p, 1) for m < 0, where the first
    # form's terms cancel and m p overflows (m = -1e200: -inf).
    value = jnp.where(m < 0, rf[0] - (m / 3) * rd[1], p_safe * rf[0] + (m * p_safe / 3) * rd[0])
    # E(1) = 1; m > 1 is outside the domain (NaN, as K).
    return jnp.where(safe, value, jnp.where(p == 0, jnp.ones_like(p), jnp.nan))


@_ellipe.defjvp
def _ellipe_jvp(primals, tangents):
    m, p = primals
    m_dot, _ = tangents
    safe = p > 0
    p_safe = jnp.where(safe, p, jnp.ones_like(p))
    rf, rd = _carlson_rf_rd(jnp.zeros_like(p), jnp.ones_like(p), p_safe)
    # dE/dm = (E - K) / (2 m) = (p R_D(0, 1, p) / 3 - K) / 2: no division by m.
    slope = jnp.where(safe, (p_safe * rd / 3 - rf) / 2, -jnp.inf * jnp.ones_like(p))
    return _ellipe(m, p), slope * m_dot


def ellipe(m: Scalar) -> ScalarOut:
    """Complete elliptic integral of the second kind ``E(m)``, as ``scipy.special.ellipe``.

    The derivative is the closed form ``dE/dm = (E - K) / (2 m)``, without the division.

    **Arguments:**

    - `m`: the parameter ``m = k**2 <= 1``, float32 or float64.

    **Returns:** ``E(m)``, shaped as `m`: ``E(1) = 1``, NaN for ``m > 1`` or NaN input.
    """
    m, p = _as_pair(m, "m", complementary=False)
    return compiled_once(_ellipe)(m, p)


# --------------------------------------------------------------------------------------------------
# Incomplete integrals


def _split_pi(dtype) -> tuple[float, float]:
    """``pi = hi + lo`` with ``hi`` 12 bits short of ``dtype``'s precision (Cody & Waite)."""
    bits = np.finfo(dtype).nmant + 1 - 12
    hi = float(np.ldexp(np.floor(np.ldexp(np.pi, bits - 2)), 2 - bits))
    lo = (np.pi - hi) + 1.2246467991473532e-16  # np.pi - hi is exact; the constant is pi - np.pi
    return hi, lo


def _reduce_pi(phi):
    """``phi = j pi + r`` with ``|r| <= pi/2``; ``r`` to ~1 ulp for ``|j| < 2**12`` (``j pi`` exact)."""
    hi, lo = _split_pi(phi.dtype)
    j = jnp.round(phi / jnp.pi)
    return j, (phi - j * hi) - j * lo


def _legendre_parts(phi, m, p):
    """Pieces shared by ``F(phi|m)``, ``E(phi|m)`` and their derivatives.

    ``phi = j pi + r`` with ``|r| <= pi/2``; ``F(phi) = 2 j K + F(r)``, likewise for ``E``. Returns
    a dict with ``j``, ``s = sin r``, ``c = cos r >= 0``, ``delta = sqrt(1 - m s^2)``, ``rf =
    R_F(c^2, 1, delta^2)``, ``rd = R_D(c^2, 1, delta^2)``, ``rd_swapped = R_D(c^2, delta^2, 1)`` and
    the complete ``rf0 = K``, ``rd0 = R_D(0, 1, p)``, ``rd0_swapped = R_D(0, p, 1)``, all with unsafe
    inputs (``m = 1``) replaced by harmless ones.
    """
    j, r = _reduce_pi(phi)
    s, c = jnp.sin(r), jnp.cos(r)
    c = jnp.abs(c)  # |r| <= pi/2 up to rounding
    m1 = p == 0
    p_safe = jnp.where(m1, jnp.ones_like(p), p)
    m_safe = jnp.where(m1, jnp.zeros_like(m), m)
    # 1 - m s^2 without cancellation near m = 1: c^2 + p s^2.
    delta2 = c * c + p_safe * s * s
    one = jnp.ones_like(s)
    rf, rd = _carlson_rf_rd(
        jnp.stack([c * c, jnp.zeros_like(c), c * c, jnp.zeros_like(c)]),
        jnp.stack([one, one, delta2, p_safe]),
        jnp.stack([delta2, p_safe, one, one]),
    )
    return dict(
        j=j,
        s=s,
        c=c,
        m1=m1,
        m=m_safe,
        p=p_safe,
        delta=jnp.sqrt(delta2),
        rf=rf[0],
        rd=rd[0],
        rd_swapped=rd[2],
        rf0=rf[1],
        rd0_swapped=rd[3],
        rd0=rd[1],
    )


def _legendre_values(q):
    """``F(phi|m)`` and ``E(phi|m)`` from the parts.

    ``F = s R_F(c^2, delta^2, 1)`` (DLMF 19.25.5); ``E`` in the form of DLMF 19.25(ii) whose terms
    are all >= 0: ``E = p F + (m p / 3) s^3 R_D(c^2, 1, delta^2) + m s c / delta`` for ``0 <= m <= 1``
    and ``E = F - (m / 3) s^3 R_D(c^2, delta^2, 1)`` (DLMF 19.25.9) for ``m < 0``, where the first
    form's terms would cancel (``m = -1e18``, ``phi = 1e-8``: ``5.2e-8`` from terms of ``1e10``).
    """
    j, s, c, m, p, delta = q["j"], q["s"], q["c"], q["m"], q["p"], q["delta"]
    f_r = s * q["rf"]
    e_r = jnp.where(
        m < 0,
        f_r - (m / 3) * s**3 * q["rd_swapped"],
        p * f_r + (m * p / 3) * s**3 * q["rd"] + m * s * c / delta,
    )
    e0 = jnp.where(m < 0, q["rf0"] - (m / 3) * q["rd0_swapped"], p * q["rf0"] + (m * p / 3) * q["rd0"])
    f = f_r + 2 * j * q["rf0"]
    e = e_r + 2 * j * e0
    # m = 1: F = atanh(sin r) + 2 j K with K = inf, E = sin r + 2 j.
    zero = jnp.zeros_like(s)
    f1 = jnp.arctanh(s) + jnp.where(j == 0, zero, jnp.sign(j) * jnp.inf)
    e1 = s + 2 * j
    return jnp.where(q["m1"], f1, f), jnp.where(q["m1"], e1, e), f_r


@jax.custom_jvp
def _legendre(phi, m, p):
    """``(F(phi|m), E(phi|m))``; the derivative uses the tangents of ``phi`` and ``m`` (not ``p``)."""
    f, e, _ = _legendre_values(_legendre_parts(phi, m, p))
    return f, e


@functools.partial(_legendre.defjvp, symbolic_zeros=True)
def _legendre_jvp(primals, tangents):
    phi, m, p = primals
    phi_dot, m_dot, _ = tangents
    q = _legendre_parts(phi, m, p)
    f, e, f_r = _legendre_values(q)
    j, s, c, pp, delta = q["j"], q["s"], q["c"], q["p"], q["delta"]
    delta = jnp.where(q["m1"], c, delta)
    f_terms, e_terms = [(1 / delta, phi_dot)], [(delta, phi_dot)]
    if not _is_zero(m_dot):
        # dF/dm = s^3 R_D(c^2, 1, delta^2) / 6 + 2 j dK/dm (DLMF 19.18.1, dK/dm = R_D(0, 1, p) / 6).
        df_dm = s**3 * q["rd"] / 6 + j * q["rd0"] / 3
        # dE/dm = (E - F) / (2 m) = -s^3 R_D(c^2, delta^2, 1) / 6 + ... (DLMF 19.25.9): no cancellation.
        de_dm = -(s**3) * q["rd_swapped"] / 6 + j * (pp * q["rd0"] / 3 - q["rf0"])
        # m = 1: dF/dm = s^3 R_D(c^2, 1, c^2) / 6 (DLMF 19.18.1 at delta = c), finite for |r| <
        # pi/2, plus 2 j dK/dm = inf j; dE/dm = (sin r - atanh(sin r)) / 2 - inf j.
        inf = jnp.full_like(s, jnp.inf)
        zero = jnp.zeros_like(s)
        c_safe = jnp.where(c > 0, c, jnp.ones_like(c))
        _, rd_at_1 = _carlson_rf_rd(c_safe * c_safe, jnp.ones_like(c), c_safe * c_safe)
        df_dm_1 = jnp.where(c > 0, s**3 * rd_at_1 / 6, inf)
        df_dm = jnp.where(q["m1"], df_dm_1 + jnp.where(j == 0, zero, j * inf), df_dm)
        de_dm = jnp.where(q["m1"], (s - jnp.arctanh(s)) / 2 - jnp.where(j == 0, zero, j * inf), de_dm)
        f_terms.append((df_dm, m_dot))
        e_terms.append((de_dm, m_dot))
    return (f, e), (_linear(f_terms, f), _linear(e_terms, e))


def _legendre_checked(phi, m, p):
    """``_legendre`` with NaN for ``m > 1`` (``p < 0``), where its forms would give numbers."""
    bad = p < 0
    f, e = _legendre(phi, jnp.where(bad, jnp.zeros_like(m), m), jnp.where(bad, jnp.ones_like(p), p))
    return jnp.where(bad, jnp.nan, f), jnp.where(bad, jnp.nan, e)


def ellipkinc(phi: Scalar, m: Scalar) -> ScalarOut:
    """Incomplete elliptic integral of the first kind ``F(phi | m)``, as ``scipy.special.ellipkinc``.

    **Arguments:**

    - `phi`: the amplitude (rad), any real value: ``F(phi + j pi) = F(phi) + 2 j K(m)``.
    - `m`: the parameter ``m = k**2 <= 1``, broadcast against `phi`.

    **Returns:** ``F(phi | m)``: ``atanh(sin(phi))`` at ``m = 1`` for ``|phi| < pi/2`` and ``+-inf``
    beyond; NaN for ``m > 1`` or NaN input.
    """
    phi, m = common_float(phi, m, names=["phi", "m"])
    phi, m = _broadcast((phi, m), ("phi", "m"))
    return compiled_once(_legendre_checked)(phi, m, 1 - m)[0]


def ellipeinc(phi: Scalar, m: Scalar) -> ScalarOut:
    """Incomplete elliptic integral of the second kind ``E(phi | m)``, as ``scipy.special.ellipeinc``.

    **Arguments:**

    - `phi`: the amplitude (rad), any real value: ``E(phi + j pi) = E(phi) + 2 j E(m)``.
    - `m`: the parameter ``m = k**2 <= 1``, broadcast against `phi`.

    **Returns:** ``E(phi | m)``; NaN for ``m > 1`` or NaN input.
    """
    phi, m = common_float(phi, m, names=["phi", "m"])
    phi, m = _broadcast((phi, m), ("phi", "m"))
    return compiled_once(_legendre_checked)(phi, m, 1 - m)[1]


# --------------------------------------------------------------------------------------------------
# Jacobi elliptic functions


@jax.custom_jvp
def _ellipj(u, m, p):
    """``(sn, cn, dn, am)`` with ``p = 1 - m``; the derivative uses the tangents of ``u`` and ``m``."""
    return _jacobi_values(u, m, p)


@functools.partial(_ellipj.defjvp, symbolic_zeros=True)
def _ellipj_jvp(primals, tangents):
    u, m, p = primals
    u_dot, m_dot, _ = tangents
    sn, cn, dn, am = out = _ellipj(u, m, p)
    terms = [[(d, u_dot)] for d in (cn * dn, -sn * dn, -m * sn * cn, dn)]
    if not _is_zero(m_dot):
        for t, d in zip(terms, _ellipj_dm(u, m, p, sn, cn, dn, am), strict=True):
            t.append((d, m_dot))
    return out, tuple(_linear(t, o) for t, o in zip(terms, out, strict=True))


def _ellipj_dm(u, m, p, sn, cn, dn, am):
    """``d(sn, cn, dn, am)/dm``."""
    # m and p may have fewer axes than u (one body, many times): broadcast them to the output.
    m, p = (jnp.broadcast_to(x, sn.shape) for x in (m, p))
    m1 = p == 0
    p_safe = jnp.where(m1, jnp.ones_like(p), p)
    m_safe = jnp.where(m1, jnp.zeros_like(m), m)
    one = jnp.ones_like(sn)

    # d am/dm = -dn dF(phi|m)/dm at phi = am: F(am) = 2 j K + F(r), r = am - j pi, sin r = (-1)^j sn.
    j = jnp.round(am / jnp.pi)
    sign = 1 - 2 * jnp.mod(j, 2)
    dn2 = jnp.where(m1, one, cn * cn + p_safe * sn * sn)
    _, rd = _carlson_rf_rd(
        jnp.stack([cn * cn, jnp.zeros_like(cn)]), jnp.stack([one, one]), jnp.stack([dn2, p_safe])
    )
    g = sign * sn**3 * rd[0] / 6 + j * rd[1] / 3
    dam = -dn * g
    dsn = cn * dam
    dcn = -sn * dam
    # dn^2 = 1 - m sn^2  =>  d dn/dm = -sn^2 / (2 dn) - m sn cn (d am/dm) / dn.
    ddn = -(sn * sn) / (2 * jnp.where(dn > 0, dn, one)) + m_safe * sn * cn * g

    # m = 1 (A&S 16.15): with t = tanh u, w = (sinh u cosh u - u) sech u = sinh u - u sech u,
    # d sn = -(t - u sech^2) / 4, d cn = t w / 4, d dn = -t (sinh u + u sech u) / 4, d am = -w / 4.
    t, sech = _tanh_sech(u)
    w = jnp.sinh(u) - u * sech
    limit = (-(t - u * sech * sech) / 4, t * w / 4, -t * (jnp.sinh(u) + u * sech) / 4, -w / 4)
    return tuple(jnp.where(m1, lim, d) for lim, d in zip(limit, (dsn, dcn, ddn, dam), strict=True))


def ellipj(u: Scalar, m: Scalar) -> tuple[ScalarOut, ScalarOut, ScalarOut, ScalarOut]:
    """Jacobi elliptic functions ``(sn, cn, dn, am)`` of ``u``, as ``scipy.special.ellipj``.

    Accurate up to ``m = 1``: ``m = 0`` gives ``(sin u, cos u, 1, u)``, ``m = 1`` gives ``(tanh u, sech u,
    sech u, gd u)``. The error is a few ulp of ``|f| + |u df/du|``, i.e. of the conditioning in ``u``.
    Differentiable in ``u`` and ``m`` (closed-form derivatives, finite at ``m = 0`` and ``m = 1``). A
    float ``m`` cannot lie closer to 1 than ``eps / 2``; below that use ``ellipj_m1(u, p)``.

    **Arguments:**

    - `u`: the argument, ``|u| <= 0.5 / eps`` (float64: 2.3e15, float32: 4.2e6), beyond which
      the rounding of ``u`` alone is about a radian.
    - `m`: the parameter, ``0 <= m <= 1``, broadcast against `u`.

    **Returns:** ``(sn, cn, dn, am)``, each of the broadcast shape; NaN outside ``0 <= m <= 1`` or
    beyond that ``|u|`` (except at ``m = 1``, which is not periodic).
    """
    u, m = common_float(u, m, names=["u", "m"])
    u, m = _broadcast((u, m), ("u", "m"))
    return compiled_once(_ellipj_checked)(u, m, 1 - m)


def ellipj_m1(u: Scalar, p: Scalar) -> tuple[ScalarOut, ScalarOut, ScalarOut, ScalarOut]:
    """Jacobi elliptic functions ``ellipj(u, 1 - p)`` of the complementary parameter ``p = 1 - m``.

    Accurate for ``p`` down to the smallest normal number, where ``m = 1 - p`` would round to 1.
    Derivatives are with respect to ``p`` (``d/dp = -d/dm``).

    **Arguments:**

    - `u`: the argument, ``|u| <= 0.5 / eps`` as for :func:`ellipj`.
    - `p`: the complementary parameter, ``0 <= p <= 1``, broadcast against `u`.

    **Returns:** ``(sn, cn, dn, am)``, each of the broadcast shape; NaN outside ``0 <= p <= 1`` or
    beyond that ``|u|``.
    """
    u, p = common_float(u, p, names=["u", "p"])
    u, p = _broadcast((u, p), ("u", "p"))
    return compiled_once(_ellipj_checked)(u, 1 - p, p)


def _ellipj_checked(u, m, p):
    # Beyond |u| = 0.5 / eps the rounding of u alone is about a radian: the values would be noise
    # (from 4e15 on in float64 they broke dn^2 + m sn^2 = 1, then turned NaN or 4e18).
    # (m = 1 is not periodic: tanh, sech and gd keep their limits.)
    beyond = (jnp.abs(u) > 0.5 / float(jnp.finfo(u.dtype).eps)) & (p != 0)
    bad = (m < 0) | (p < 0) | jnp.isnan(m) | jnp.isnan(p)
    if jnp.size(m) < jnp.size(u):
        # m and p of a body read at many u: masked by u's test they took u's shape, and all that
        # the series derive from them (:func:`.jacobi._jacobi_parameters`: the AGM, the nome) was
        # computed again at every u. With one u per m, masking m and p by it fused better (10^4
        # bodies' omega and q at one time 4.0 against 4.4 ms).
        u, failed = jnp.where(beyond, jnp.zeros_like(u), u), bad | beyond
    else:
        bad = failed = bad | beyond
    m_ok = jnp.where(bad, jnp.zeros_like(m), m)
    p_ok = jnp.where(bad, jnp.ones_like(p), p)
    out = _ellipj(u, m_ok, p_ok)
    return tuple(jnp.where(failed, jnp.nan, o) for o in out)
