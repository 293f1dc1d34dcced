"""The phase integral of a Cayley-Klein half of Lagrange's top by Jacobi's theta form.

A half whose pole is ``u = -k`` turns at ``(b + k a) / (1 + k u)``, and ``1 + k u = P cn^2 + P' sn^2``
(``P``, ``P'`` its values on the start and the other turning circle, both ``>= 0``). The integral of
``1 / (1 + k u)`` is brought to ``G(x) = int_0^x dx' / (1 + n sn^2(x' | m))`` with ``n >= 0``, the form
that :mod:`.precession` evaluates per sample as ``g x + c V(x)`` with one theta product:

- ``P <= P'`` (the pole lies beyond the start circle): ``1 / (1 + k u) = 1 / (P (1 + n sn^2 tau))``,
  ``n = (P' - P) / P``.
- ``P > P'`` (the pole lies between the other circle and the cubic's third root): half a period on,
  ``w = tau - K``, ``1 + k u = P' (1 + n' sn^2 w) / dn^2 w`` with ``n' = (m - N) / (N - 1)``,
  ``N = (P - P') / P`` (DLMF 19.7.10), and ``dn^2 / (1 + n' sn^2) = (1 + m / n') / (1 + n' sn^2) - m / n'``.

Both ``n`` and ``m / n`` are finite and formed from the roots without cancellation, so the slope ``g``
and its deficit ``1 - g`` are taken from positive sums where either is small: near a pole
(``n -> inf``), where the phase steps by nearly ``pi`` at each pass, the slope is ``O(1 / sqrt(n))``
and is taken from the theta series at ``K' - beta`` rather than as ``1 - c Im Z(i beta)``.
"""

import jax
import jax.numpy as jnp
import numpy as np

from .carlson import _carlson_rf_rd, _steps
from .elliptic import _nome_parts, _sin_cos
from .precession import _THETA_FACTORS, _im_zeta, _lower_terms, _reduce, _upper_zeta

# Cephes' atan: z + z^3 P(z^2) / Q(z^2) on |z| <= 0.66, within 1 ulp.
_ATAN_P = (-8.750608600031904122785e-1, -1.615753718733365076637e1, -7.500855792314704667340e1,
           -1.228866684490136173410e2, -6.485021904942025371773e1)  # fmt: skip
_ATAN_Q = (2.485846490142306297962e1, 1.650270098316988542046e2, 4.328810604912902668951e2,
           4.853903996359136964868e2, 1.945506571482613964425e2)  # fmt: skip


@jax.custom_jvp
def _atan2(y, x):
    """``atan2(y, x)`` within 1 ulp (0 at the origin, ``+pi`` on the negative real axis) from a
    rational approximation that vectorises: XLA's ``atan2`` is a call per element on CPU (measured
    10x the cost). ``min(|x|, |y|) / max(|x|, |y|)`` is reduced by ``atan z = pi/4 + atan((z - 1) /
    (z + 1))`` above 0.66."""
    ax, ay = jnp.abs(x), jnp.abs(y)
    big, small = jnp.maximum(ax, ay), jnp.minimum(ax, ay)
    z = small / jnp.where(big > 0, big, 1.0)
    far = z > 0.66
    w = jnp.where(far, (z - 1) / (z + 1), z)
    w2 = w * w
    p, q = _ATAN_P[0], w2 + _ATAN_Q[0]
    for a, b in zip(_ATAN_P[1:], _ATAN_Q[1:], strict=True):
        p, q = p * w2 + a, q * w2 + b
    angle = w + w * (w2 * p / q)
    angle = jnp.where(far, np.pi / 4 + angle, angle)
    angle = jnp.where(ay > ax, np.pi / 2 - angle, angle)
    angle = jnp.where(x < 0, np.pi - angle, angle)
    return jnp.where(y < 0, -angle, angle)


@_atan2.defjvp
def _atan2_jvp(primals, tangents):
    (y, x), (y_dot, x_dot) = primals, tangents
    r2 = x * x + y * y
    r2 = jnp.where(r2 > 0, r2, 1.0)
    return _atan2(y, x), (x * y_dot - y * x_dot) / r2


def _quarter(upper, agm, big_l):
    """``K`` from :func:`.elliptic._nome_parts` (``inf`` at ``m = 1``)."""
    return jnp.where(upper, big_l, jnp.pi) / (2 * agm)


def _quarter_period(m, p):
    upper, agm, _, big_l = _nome_parts(m, p)
    return _quarter(upper, agm, big_l)


def _theta_parts(m, p, n, ratio):
    """Per body: ``G(x) = int_0^x dx' / (1 + n sn^2(x' | m)) = g x + c V(x)`` for ``n > 0``.

    The construction of :func:`.precession._precession_parts` (Jacobi's form with the imaginary
    parameter ``i beta``, ``sc^2(beta | 1 - m) = n / m``), written in ``ratio = m / n`` so that
    ``m = 0`` (a top whose centre of mass is at the pivot) needs no infinite ``n / m``:
    ``beta = R_F(ratio, ratio (1 + n), 1 + ratio)`` by the homogeneity of ``R_F``, and
    ``c = 1 / sqrt((1 + ratio) (1 + n))``. The slope is returned with its deficit ``1 - g``; for
    ``m <= 1/2`` and ``beta`` measured from ``K'`` (``n > ratio``, ``beta' = K' - beta``) the slope is
    ``c (pi / (2 K) + Im Z(i beta'))`` (from ``Z(u + i K') = Z(u) + cn dn / sn (u) - i pi / (2 K)``), a
    positive sum that keeps its relative accuracy as ``n -> inf``, where ``1 - c Im Z(i beta)`` cancels.

    **Arguments:**

    - `m`, `p`: the parameter and ``p = 1 - m``.
    - `n`: the characteristic, ``> 0``; `ratio`: ``m / n`` (``>= 0``, finite).

    **Returns:** a dict with ``quarter`` (``K``, ``inf`` at ``m = 1``), ``slope`` (``g``), ``deficit``
    (``1 - g``), ``c``, and the fields that :func:`.precession._precession_phase` reads.
    """
    upper, agm, nome, big_l = _nome_parts(m, p)
    finite_l = jnp.isfinite(big_l)
    quarter = _quarter(upper, agm, big_l)

    from_zero = n <= ratio  # n <= sqrt(m)
    ratio_safe = jnp.where(from_zero, ratio, 1.0)
    args = (
        jnp.where(from_zero, ratio_safe, n),
        jnp.where(from_zero, ratio_safe * (1 + n), n + m),
        jnp.where(from_zero, 1 + ratio_safe, 1 + n),
    )
    shift, _ = _carlson_rf_rd(*args, with_rd=False)  # beta or K' - beta
    c_factor = 1 / jnp.sqrt((1 + ratio) * (1 + n))
    factors = _steps(_THETA_FACTORS, m.dtype)
    nome2 = nome * nome

    b, (_, cos_b, sin_2b, cos_2b), zeta = _upper_zeta(agm, shift, from_zero, nome, factors)
    slope_upper = ratio / (1 + ratio) + c_factor * agm * zeta
    deficit_upper = 1 / (1 + ratio) - c_factor * agm * zeta

    # m <= 1/2 (from K': y' = agm beta').
    e, r_lower, s_lower, gap_lower = _lower_terms(agm, shift, from_zero, nome)

    def im_zeta(r, s, gap):
        return _im_zeta(r, s, gap, nome2, factors)

    deficit_lower = c_factor * agm * im_zeta(r_lower, s_lower, gap_lower)
    r_prime = jnp.where(from_zero, 0.0, nome * jnp.exp(e))
    near_pole = c_factor * agm * (1 + im_zeta(r_prime, nome * jnp.exp(-e), 1 - r_prime))
    slope_lower = jnp.where(from_zero, 1 - deficit_lower, near_pole)

    # The factors of _theta_phase in pairs (k >= 1): A + B X + i C Y, the per-sample X, Y below.
    pairs = []
    r_k, s_k, power = r_lower, s_lower, jnp.ones_like(nome2)
    for _ in range(factors - 1):
        r_k, s_k, power = r_k * nome2, s_k * nome2, power * nome2
        pairs.append(
            (
                jnp.where(upper, 1 + power * power * nome2, (1 - r_k) * (1 - s_k)),
                jnp.where(upper, power * cos_2b, r_k + s_k),
                jnp.where(upper, power * sin_2b, r_k - s_k),
            )
        )
    return dict(
        quarter=quarter,
        slope=jnp.where(upper, slope_upper, slope_lower),
        deficit=jnp.where(upper, deficit_upper, deficit_lower),
        c=c_factor,
        upper=upper,
        agm=agm,
        two_l=jnp.where(upper & finite_l, 2 * jnp.where(finite_l, big_l, 1.0), jnp.inf),
        b=jnp.where(upper, b, 0.0),
        bend=(2 * cos_b * cos_b, sin_2b, cos_2b),
        lead=(gap_lower * (1 - s_lower), r_lower + s_lower, r_lower - s_lower),
        pairs=pairs,
    )


def _theta_phase(x, parts):
    """``V(x)`` of :func:`_theta_parts` (odd in the reduced ``rho``, ``x = rho + 2 j K``, stepping by
    ``2 b`` per period): the phase of :func:`.precession._precession_phase`'s theta product, whose
    factors are taken in conjugate pairs ``(1 + sigma r w)(1 + sigma s conj(w))`` with coefficients per
    body, so that a sample costs one ``sin``/``cos`` pair, one ``exp``/``expm1`` pair, a real-coefficient
    complex product and one ``atan2``.

    - ``m <= 1/2`` (``r``, ``s`` per body, ``w = e^(-2 i y)``): a pair is
      ``(1 - r)(1 - s) + (r + s) X + i (r - s) Y`` with ``X = 2 sin^2 y``, ``Y = sin 2y``; the leading
      pair with ``1 - r`` from its own expression (it vanishes at a pole).
    - ``m > 1/2`` (``w = e^(-2 i b)`` per body, ``r = e^(-2y)``, ``s = e^(2y - 2L)``): a pair is
      ``1 + q'^(4k+2) + q'^(2k) (cos 2b X + i sin 2b Y)`` with ``X = r + s``, ``Y = s - r``; the leading
      one as the product of its two factors, whose real parts are formed without cancellation.
    """
    turns, rho = _reduce(x, parts["quarter"])
    upper = parts["upper"]
    sign = jnp.where(rho < 0, -1.0, 1.0).astype(rho.dtype)
    y = parts["agm"] * (sign * rho)
    sin_y, cos_y = _sin_cos(y)
    e = jnp.expm1(-2 * y)
    r, s = 1 + e, jnp.exp(2 * y - parts["two_l"])
    big_x = jnp.where(upper, r + s, 2 * sin_y * sin_y)
    big_y = jnp.where(upper, s - r, 2 * sin_y * cos_y)
    a0, b0, c0 = parts["lead"]
    bend, sin_2b, cos_2b = parts["bend"]
    re = jnp.where(upper, (r * bend - e) * (1 + s * cos_2b) + r * s * sin_2b * sin_2b, a0 + b0 * big_x)
    im = jnp.where(upper, (s - r) * sin_2b, c0 * big_y)
    for a_k, b_k, c_k in parts["pairs"]:
        f_re, f_im = a_k + b_k * big_x, c_k * big_y
        re, im = re * f_re - im * f_im, re * f_im + im * f_re
    b = parts["b"]
    return sign * (b + _atan2(im, re)) + 2 * turns * b


def _start_phase(sn0, cn0, dn0, p, quarter):
    """``tau0 = F(am0 | m)`` reduced to ``[-K, K]`` (``cn0 < 0``: ``tau0 = rho0 +- 2K``) from
    ``(sn0, cn0, dn0)``: Carlson's ``R_F`` (DLMF 19.25.5) on ``|sn| <= 1/sqrt 2``, measured back from
    ``K`` above (accurate as ``p -> 0``); ``atanh(sn0)`` on the separatrix (``p = 0``)."""
    s, c = jnp.abs(sn0), jnp.abs(cn0)
    direct = s * s <= 0.5
    pc = jnp.where(p > 0, p, 1.0)
    rf, _ = _carlson_rf_rd(jnp.where(direct, c * c, pc * s * s), dn0 * dn0, jnp.where(direct, 1.0, pc), False)
    quarter_safe = jnp.where(jnp.isfinite(quarter), quarter, 1.0)
    c_safe = jnp.where(c > 0, c, 1.0)
    f = jnp.where(direct, s * rf, jnp.where(p > 0, quarter_safe - c * rf, jnp.log((1 + s) / c_safe)))
    sign_s = jnp.where(sn0 < 0, -1.0, 1.0).astype(sn0.dtype)
    sign_c = jnp.where(cn0 < 0, -1.0, 1.0).astype(sn0.dtype)
    return sign_c * sign_s * f
