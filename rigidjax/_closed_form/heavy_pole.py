"""The first-order terms in ``b + k a`` of a Cayley-Klein half of Lagrange's top whose pole
(``u = -k``) is a root of the cubic, where ``b + k a = 0``: a top with ``w3 = 0`` and ``L_z = 0``
(released from rest, swinging in a vertical plane), one swinging through the vertical.

The half's phase term ``(b + k a) int_0^t dt / (1 + k u)`` is zero there, but not its derivative:
``d(b + k a)`` times the integral on the motion, or the first-order shift of a half that passes
through its pole. Both are given here, zero in value (multiplied by ``b + k a``) and without
derivatives of their own (so only first derivatives are the motion's), in ``E(x) = E(am x | m)``
(Jacobi's epsilon) with ``x = tau0 + lambda t`` on the elliptic form ``1 + k u = P cn^2 + P' sn^2``:

- The pole on the third root (not reached): ``P' = P (1 - m)``, ``1 + k u = P dn^2``, and the
  integral is ``int nd^2 / (lambda P) = [E(x) - m sn cn / dn] / (lambda P')``.
- The pole on a turning circle (reached: the half is ``S e``, ``S = sqrt(P_far / 2) J(x)`` signed,
  ``J = sn`` or ``cn``, ``e`` a uniformly turning unit phase): to first order the half is
  ``(S + i (b + k a) R) e``, ``R = J (A(x) - A_0) / (4 lambda sqrt(P_far / 2))``, where ``A`` is the
  antiderivative of ``1 / J^2`` (``x - E - cn dn / sn``; ``(p x - E + sn dn / cn) / p``), its double
  pole passed by its finite part, and ``A_0`` is ``A(tau0)`` plus the turn that the pole form's
  direction (from ``q0`` and its rate) takes with ``b + k a``; ``J A`` and ``A_0`` are written
  without division by ``J``. ``dR/dt = Q / 4`` with ``Q = (1 + 4 R dS/dt) / S``, likewise finite.
"""

import jax
import jax.numpy as jnp

from .._numerics import safe_sqrt
from .carlson import _carlson_rf_rd
from .precession import _reduce


def taken_as_zero(x, mask):
    """``x`` as zero in value where ``mask``, keeping its derivative: a top in the family above up to
    the rounding of its inputs is taken as in it (the general form's derivatives are not the
    motion's there)."""
    return jnp.where(mask, x - jax.lax.stop_gradient(x), x)


def _epsilon(s, c, m, p):
    """``E(am r | m)`` for ``0 <= r <= K`` from ``s = sn r``, ``c = cn r`` (both ``>= 0``), and the complete
    ``E(m)``, in the form of DLMF 19.25(ii) whose terms are all ``>= 0`` (``0 <= m < 1``)."""
    s, c, m, p = jnp.broadcast_arrays(s, c, m, p)
    d2 = c * c + p * s * s
    zero, one = jnp.zeros_like(s), jnp.ones_like(s)
    rf, rd = _carlson_rf_rd(jnp.stack([c * c, zero]), jnp.stack([one, one]), jnp.stack([d2, p]))
    partial = p * s * rf[0] + (m * p / 3) * s**3 * rd[0] + m * s * c / jnp.sqrt(d2)
    return partial, p * rf[1] + (m * p / 3) * rd[1]


def epsilon_step(now, start, rho0, v, m, p, quarter):
    """``E(x) - E(tau0)`` for ``x = tau0 + v``: ``now`` and ``start`` are ``(sn, cn, dn)`` at ``x`` and
    ``tau0``, ``rho0`` is ``tau0`` reduced to ``[-K, K]`` (``E`` steps by ``2 E(m)`` per period)."""
    turns, rho = _reduce(rho0 + v, quarter)
    s = jnp.stack(jnp.broadcast_arrays(jnp.abs(now[0]), jnp.abs(start[0])))
    c = jnp.stack(jnp.broadcast_arrays(jnp.abs(now[1]), jnp.abs(start[1])))
    partial, complete = _epsilon(s, c, m, p)
    sign = jnp.where(rho < 0, -1.0, 1.0).astype(rho.dtype)
    sign0 = jnp.where(rho0 < 0, -1.0, 1.0).astype(rho.dtype)
    return 2 * turns * complete[0] + sign * partial[0] - sign0 * partial[1]


def pole_root_terms(now, start, step, v, rate, m, p, near, far):
    """Per half: the integral ``int_0^t dt / (1 + k u)`` of a half whose pole is the third root, and
    ``R``, ``dR/dt`` of one whose pole is a turning circle (see the module docstring); ``step`` is
    :func:`epsilon_step`, ``v = lambda t``. Finite where the forms do not apply."""
    sn, cn, dn = now
    sn0, cn0, dn0 = start
    ok = (rate > 0) & (p > 0)
    rate_s, p_s = jnp.where(ok, rate, 1.0), jnp.where(ok, p, 1.0)
    far_s = jnp.where(far > 0, far, 1.0)
    integral = (step - m * (sn * cn / dn - sn0 * cn0 / dn0)) / (rate_s * far_s)
    scale = safe_sqrt(jnp.maximum(near, far) / 2)
    scale_s = jnp.where(scale > 0, scale, 1.0)
    # J = sn (the start circle is the pole) and J = cn (the other circle is).
    gap_sn = v - step - m * sn0 * cn0**3 * dn0 / (sn0 * sn0 + cn0 * cn0 * dn0 * dn0)
    r_sn = sn * gap_sn - cn * dn
    q_sn = sn * (1 + m * cn * cn) + cn * dn * gap_sn
    spread = cn0 * cn0 + sn0 * sn0 * dn0 * dn0
    gap_cn = (
        v - step / p_s - m * sn0 * cn0 * dn0 * (1 + sn0 * sn0) / (p_s * jnp.where(spread > 0, spread, 1.0))
    )
    r_cn = cn * gap_cn + sn * dn / p_s
    q_cn = cn * (p - m * sn * sn) / p_s - sn * dn * gap_cn
    start_is_pole = near <= far
    r = jnp.where(start_is_pole, r_sn, r_cn) / (4 * rate_s * scale_s)
    r_dot = jnp.where(start_is_pole, q_sn, q_cn) / (4 * scale_s)
    valid = ok & (scale > 0)
    return (
        jnp.where(ok & (far > 0), integral, 0.0),
        jnp.where(valid, r, 0.0),
        jnp.where(valid, r_dot, 0.0),
    )
