"""The torque-free body's orientation in closed form: the precession angle about the angular
momentum by Jacobi's theta form of the elliptic integral of the third kind, and the nutation and spin
from the body-frame momentum (see :func:`rigidjax.torque_free_motion`)."""

import jax
import jax.numpy as jnp
import numpy as np

from .._kinematics.quaternion import _quat_multiply
from .._numerics import safe_norm_of, safe_sqrt
from .barrier import _held_per_body, _materialised
from .carlson import _CARLSON_STEPS, _carlson_rf_rd, _rf_series, _steps
from .frame import _clip, _cycle, _safe_div
from .jacobi import _mod, _nome_parts, _sin_cos

# Factors of the theta products in _precession_phase: with q <= exp(-pi) the last omitted one differs
# from 1 by at most q^(2 J) (float64: 4e-17; float32: 7e-9).
_THETA_FACTORS = {np.dtype(np.float32): 3, np.dtype(np.float64): 6}


def _precession_parts(m, p, n, nu, start):
    """Per body: what the precession integral ``G(tau) = int_0^tau dtau' / (1 + n sn^2(tau')) =
    Pi(-n; am(tau) | m)`` needs, and the reduced initial phase.

    Jacobi's form of the integral of the third kind (Whittaker & Watson 22.74) with the imaginary
    parameter ``i beta``, ``sn^2(i beta | m) = -n / m``, i.e. ``sc^2(beta | 1 - m) = nu``::

        G(tau) = g tau + c V(tau),   c = sqrt(nu / ((1 + nu) (1 + n))),

    with ``V`` the phase of ``Theta(tau + i beta)`` less a part linear in ``tau``, moved into the slope
    ``g``: ``V`` is bounded and ``2K``-periodic up to a constant step per half period. It is evaluated
    as a product of theta factors in the nome of the smaller of ``m`` and ``1 - m`` (at most
    ``exp(-pi)``, as in :func:`.elliptic._jacobi_values`):

    - ``m <= 1/2``: the ordinary nome ``q``, ``V = arg Theta(tau + i beta)`` (``2K``-periodic) from
      the product ``prod (1 - q^(2j-1) e^(2 y) e^(-2 i x)) (1 - q^(2j-1) e^(-2 y) e^(2 i x))``,
      ``x + i y = pi (tau + i beta) / (2 K)``, and ``g = 1 - c Im Z(i beta)`` from its logarithmic
      derivative (``V`` is periodic; ``g = G(K) / K``).
    - ``m > 1/2``: Jacobi's imaginary transformation, the complementary nome ``q'``; ``Theta``
      becomes ``theta_2`` of ``i pi (tau + i beta) / (2 K')`` times a Gaussian, whose phase is linear
      in ``tau`` (moved into ``g = cn^2(beta | 1 - m) + c Z(beta | 1 - m)``) and steps by ``pi beta / K'``
      per half period. The product runs over ``e^(-2a) q'^(2j)``, ``a = pi |rho| / (2 K')``.

    ``beta`` is an incomplete integral of the first kind (one ``R_F`` per body), taken from 0
    (``beta = sqrt(nu) R_F(1, 1 + n, 1 + nu)``) or from ``K'`` (``K' - beta = R_F(n, n + m, 1 + n)``),
    whichever is nearer, so that the leading factors, which vanish at ``beta = K'``, keep their
    relative accuracy (``1 - r`` by ``expm1``). All terms of the slopes are positive except ``1 - c Im
    Z``, which loses ``~eps sqrt(n)`` relative for nearly symmetric bodies with ``n >> 1``.

    The initial phase: ``rho0 = F(am0 | m)`` reduced to ``[-K, K]`` from ``(sn0, cn0, dn0)``, by
    Carlson's ``R_F`` (DLMF 19.25.5), ``|sn| R_F(cn^2, dn^2, 1)``, on ``|sn| <= 1/sqrt 2`` and wherever
    ``cn^2 > p``; else measured back from ``K``, ``K - |cn| R_F(p sn^2, dn^2, p)``, whose arguments
    are ``O(p)`` but never zero. Near the turning point (``cn -> 0``) the direct form's derivative
    would be ``-inf`` times 0; near the separatrix (``p -> 0``) the form from ``K`` would cancel
    terms of size ``1/p`` in its derivative (off by 6e-7 at a relative 1e-12 from the separatrix).
    Stacked with ``beta``'s ``R_F`` in one duplication loop. On the separatrix (``p = 0``) the same
    formulas hold with ``K = inf``, ``q' = 0`` and ``rho0 = atanh(sn0)``.

    **Arguments:**

    - `m`, `p`: the parameter and ``p = 1 - m``; `n` ``>= 0`` and `nu` ``= n / m`` (``inf`` for
      ``m = 0 < n``; 0 for ``n = 0``).
    - `start`: ``(sn0, cn0, dn0)`` of the initial phase.

    **Returns:** a dict: ``quarter`` (``K``), ``slope`` (``g``), ``rest`` (``1 - g``, formed without
    cancelling), ``c``, ``rho0`` and what
    :func:`_precession_phase` reads.
    """
    upper, agm, nome, big_l = _nome_parts(m, p)
    finite_l = jnp.isfinite(big_l)
    l_safe = jnp.where(finite_l, big_l, 1.0)
    quarter = jnp.where(upper, jnp.where(finite_l, big_l, jnp.inf) / (2 * agm), (jnp.pi / 2) / agm)
    quarter_safe = jnp.where(jnp.isfinite(quarter), quarter, 1.0)

    # One duplication loop: the imaginary shift (from 0 or from K') and the initial phase.
    from_zero = n <= jnp.sqrt(m)
    nu_safe = jnp.where(from_zero, nu, 1.0)
    sn0, cn0, dn0 = start
    s, c = jnp.abs(sn0), jnp.abs(cn0)
    direct = (s * s <= 0.5) | (c * c > p)
    pc = jnp.where(p > 0, p, 1.0)
    args = (
        (jnp.where(from_zero, 1.0, n), jnp.where(direct, c * c, pc * s * s)),
        (jnp.where(from_zero, 1 + n, n + m), dn0 * dn0),
        (jnp.where(from_zero, 1 + nu_safe, 1 + n), jnp.where(direct, 1.0, pc)),
    )
    stacked = [jnp.stack(jnp.broadcast_arrays(*a)) for a in args]
    rf = _carlson_rf(*(a.reshape(-1) for a in stacked)).reshape(stacked[0].shape)
    shift = jnp.where(from_zero, jnp.sqrt(nu_safe), 1.0) * rf[0]  # beta or K' - beta
    # p = 0: F = atanh(s) = log((1 + s) / c), from c (not 1 - s) where s -> 1; c = 0 is steady.
    c_safe = jnp.where(c > 0, c, 1.0)
    f = jnp.where(direct, s * rf[1], jnp.where(p > 0, quarter_safe - c * rf[1], jnp.log((1 + s) / c_safe)))
    sign_s = jnp.where(sn0 < 0, -1.0, 1.0).astype(sn0.dtype)
    sign_c = jnp.where(cn0 < 0, -1.0, 1.0).astype(sn0.dtype)
    rho0 = sign_c * sign_s * f  # cn0 < 0: half a period on, tau0 = rho0 +- 2K

    # The share of the precession that the phase carries: c = sn cn / dn (beta | 1 - m).
    c_factor = jnp.sqrt(1 / ((1 + 1 / nu) * (1 + n)))
    factors = _steps(_THETA_FACTORS, m.dtype)
    nome2 = nome * nome

    b, (_, cos_b, sin_2b, cos_2b), zeta = _upper_zeta(agm, shift, from_zero, nome, factors)
    b, cos_b, sin_2b, cos_2b, zeta = _materialised((b, cos_b, sin_2b, cos_2b, zeta))
    slope_upper = 1 / (1 + nu) + c_factor * agm * zeta
    nu_upper = jnp.where(upper, nu, 1.0)  # finite there (m > 1/2); inf only for m = 0
    rest_upper = nu_upper / (1 + nu_upper) - c_factor * agm * zeta
    _, r_lower, s_lower, gap_lower = _lower_terms(agm, shift, from_zero, nome)
    rest_lower = c_factor * agm * _im_zeta(r_lower, s_lower, gap_lower, nome2, factors)
    slope_lower = 1 - rest_lower

    return dict(
        quarter=quarter,
        slope=jnp.where(upper, slope_upper, slope_lower),
        rest=jnp.where(upper, rest_upper, rest_lower),
        c=c_factor,
        rho0=rho0,
        upper=upper,
        agm=agm,
        nome2=nome2,
        l_safe=jnp.where(upper & finite_l, l_safe, jnp.inf),
        b=b,
        bend=(cos_b * cos_b, sin_2b, cos_2b),
        lower=(r_lower, s_lower, gap_lower),
    )


@jax.custom_jvp
def _carlson_rf(x, y, z):
    """Carlson's ``R_F(x, y, z)``: the duplication of :func:`.carlson._carlson_rf_rd` with its steps
    unrolled, and the result held in memory; the derivatives are those of the loop there.

    On CPU each step of the loop costs about ten dispatches of small kernels, most of the cost of
    the precession's parameters; unrolled, the steps fuse, and held in memory, the result is not
    recomputed (steps included) by each of its readers. Differentiated, the value and derivative
    are the loop's: unrolled steps would lengthen the compile (the loop's derivative is one loop).

    Every body takes the step count that arguments spread over 300 decades need, also where fewer
    would do: stopping after the first steps where all bodies had converged (a ``cond``) cost more
    than the steps it saved, as XLA on CPU then computed each of the four state arrays that cross
    it in a kernel of its own (2 x 10^4 arguments: 1.3 ms against 0.6 ms for all twelve steps).
    """
    a_f = (x + y + z) / 3
    dev_x, dev_y = a_f - x, a_f - y
    steps = _steps(_CARLSON_STEPS, x.dtype)
    _, _, _, a_f = _rf_steps((x, y, z, a_f), steps)
    scale = jnp.asarray(4.0**-steps, x.dtype)
    (rf,) = _materialised((_rf_series(dev_x, dev_y, a_f, scale),))
    return rf


def _rf_steps(state, count):
    """``count`` duplication steps of ``(x, y, z, mean)``, unrolled."""
    x, y, z, a_f = state
    for _ in range(count):
        sx, sy, sz = safe_sqrt(x), safe_sqrt(y), safe_sqrt(z)
        lam = sx * (sy + sz) + sy * sz
        x, y, z, a_f = (x + lam) / 4, (y + lam) / 4, (z + lam) / 4, (a_f + lam) / 4
    return x, y, z, a_f


@_carlson_rf.defjvp
def _carlson_rf_jvp(primals, tangents):
    # The loop's own value (the same steps): the unrolled ones are left out of differentiated programs.
    return jax.jvp(lambda *a: _carlson_rf_rd(*a, with_rd=False)[0], primals, tangents)


def _upper_zeta(agm, shift, from_zero, nome, factors):
    """``m > 1/2``: ``b = pi beta / (2 K') = agm beta`` (``shift`` is ``beta`` from 0, or from ``pi/2``
    where not ``from_zero``), ``(sin b, cos b, sin 2b, cos 2b)`` and ``Z(beta | 1 - m) / agm``, the
    logarithmic derivative of ``theta_4(b | q')`` (``nome = q'``), by ``factors`` terms."""
    angle = agm * shift
    sin_a, cos_a = _sin_cos(angle)
    sin_b, cos_b = jnp.where(from_zero, sin_a, cos_a), jnp.where(from_zero, cos_a, sin_a)
    b = jnp.where(from_zero, angle, jnp.pi / 2 - angle)
    sin_2b, cos_2b = 2 * sin_b * cos_b, (cos_b - sin_b) * (cos_b + sin_b)
    nome2 = nome * nome

    def term(_, carry):
        zeta, power = carry
        return zeta + 4 * power * sin_2b / (1 - 2 * power * cos_2b + power * power), power * nome2

    # Loops rather than unrolled terms here and in _im_zeta: smaller programs, faster to compile.
    zeta, _ = jax.lax.fori_loop(0, factors, term, tuple(jnp.broadcast_arrays(jnp.zeros_like(b), nome)))
    return b, (sin_b, cos_b, sin_2b, cos_2b), zeta


def _lower_terms(agm, shift, from_zero, nome):
    """``m <= 1/2``: ``e = 2 y`` with ``y = pi beta / (2 K) = agm beta`` and the first terms ``r = q e^(2y)``,
    ``s = q e^(-2y)`` and ``1 - r`` of the theta products (measured from ``K'`` where not ``from_zero``)."""
    e = 2 * agm * shift
    r = jnp.where(from_zero, nome * jnp.exp(e), jnp.exp(-e))
    s = jnp.where(from_zero, nome * jnp.exp(-e), nome * nome * jnp.exp(e))
    gap = jnp.where(from_zero, 1 - r, -jnp.expm1(-e))
    return e, r, s, gap


def _im_zeta(r, s, gap, nome2, factors):
    """``Im Z(i beta | m) / agm`` from the terms of :func:`_lower_terms`: a sum of positive terms."""

    def term(_, carry):
        total, r, s, gap = carry
        total = total + 2 * (r - s) / (gap * (1 - s))
        r, s = r * nome2, s * nome2
        return total, r, s, 1 - r

    r, s, gap = jnp.broadcast_arrays(r, s, gap, nome2)[:3]
    return jax.lax.fori_loop(0, factors, term, (jnp.zeros_like(r), r, s, gap))[0]


def _reduce(tau, quarter):
    """``tau = rho + 2 j K`` with ``|rho| <= K`` (``j = 0`` for ``K = inf``): ``(j, rho)``."""
    finite = jnp.isfinite(quarter)
    quarter = jnp.where(finite, quarter, 1.0)
    turns = jnp.where(finite, jnp.round(tau / (2 * quarter)), 0.0)
    return turns, tau - 2 * quarter * turns


def _precession_phase(rho, turns, body):
    """``V`` of :func:`_precession_parts` at ``tau = rho + 2 j K`` (``|rho| <= K``, ``j = turns``):
    ``G(tau) = g tau + c V``.

    ``V`` is odd in ``rho``; it is evaluated at ``|rho|`` as the phase of one theta product (the
    factors of both nomes' forms selected per body before it), with one ``atan2``, one ``sin``/``cos``
    and one ``exp``/``expm1`` pair per point. Every factor has a positive real part.
    """
    upper, agm, nome2 = body["upper"], body["agm"], body["nome2"]
    cos_b2, sin_2b, cos_2b = body["bend"]
    r_lower, s_lower, gap_lower = body["lower"]
    sign = jnp.where(rho < 0, -1.0, 1.0).astype(rho.dtype)
    x = agm * (sign * rho)  # pi |rho| / (2 K) for m <= 1/2, pi |rho| / (2 K') above
    sin_x, cos_x = _sin_cos(x)
    e = jnp.expm1(-2 * x)
    # The leading factor 1 + sigma r w (w = e^(-2ix), sigma = -1 | w = e^(-2ib), sigma = +1) has real
    # part (1 - r) + r (1 + sigma cos(arg w)), formed without cancellation where r -> 1.
    r = jnp.where(upper, 1 + e, r_lower)
    gap = jnp.where(upper, -e, gap_lower)
    s = jnp.where(upper, jnp.exp(2 * x - 2 * body["l_safe"]), s_lower)
    bend = jnp.where(upper, 2 * cos_b2, 2 * sin_x * sin_x)
    w_re = jnp.where(upper, cos_2b, 1 - 2 * sin_x * sin_x)
    w_im = jnp.where(upper, -sin_2b, -2 * sin_x * cos_x)
    sigma = jnp.where(upper, 1.0, -1.0).astype(rho.dtype)
    re, im = gap + r * bend, sigma * r * w_im
    r_j, s_j = r, s
    for k in range(_steps(_THETA_FACTORS, rho.dtype)):
        if k:
            r_j = r_j * nome2
            f_re, f_im = 1 + sigma * r_j * w_re, sigma * r_j * w_im
            re, im = re * f_re - im * f_im, re * f_im + im * f_re
        f_re, f_im = 1 + sigma * s_j * w_re, -sigma * s_j * w_im
        re, im = re * f_re - im * f_im, re * f_im + im * f_re
        s_j = s_j * nome2
    b = jnp.where(upper, body["b"], 0.0)
    return sign * (b + jnp.arctan2(im, re)) + 2 * turns * b


def _rough_angle(y, x):
    """``atan2(y, x)`` to within 0.005 rad, for counting turns only (no derivative).

    ``atan(z) ~ z (pi/4 + 0.273 (1 - z))`` on ``[0, 1]``. ``y = 0`` gives ``+pi`` on the negative ``x``
    axis, like the half-angle quaternions of :func:`_half_angles`.
    """
    y, x = jax.lax.stop_gradient(y), jax.lax.stop_gradient(x)
    ax, ay = jnp.abs(x), jnp.abs(y)
    big = jnp.maximum(ax, ay)
    z = jnp.minimum(ax, ay) / jnp.where(big > 0, big, 1.0)
    a = z * (jnp.pi / 4 + 0.273 * (1 - z))
    a = jnp.where(ay > ax, jnp.pi / 2 - a, a)
    a = jnp.where(x < 0, jnp.pi - a, a)
    return jnp.where(y < 0, -a, a)


def _half_angles(momentum):
    """Half-angle cosines and sines of the 3-1-3 angles ``theta`` (nutation, in [0, pi]) and ``psi``
    (spin, in (-pi, pi]) with ``momentum / |momentum| = (sin theta sin psi, sin theta cos psi, cos theta)``.

    Formed from the components without dividing by ``sin theta`` and without cancellation.
    """
    lx, ly, lc = momentum[..., 0], momentum[..., 1], momentum[..., 2]
    size = safe_norm_of(lx, ly, lc)
    st = safe_norm_of(lx, ly)
    up = lc >= 0
    t_cos = jnp.where(up, size + lc, st)
    t_sin = jnp.where(up, st, size - lc)
    t_norm = safe_norm_of(t_cos, t_sin)
    t_norm = jnp.where(t_norm > 0, t_norm, 1.0)
    right = ly >= 0
    sign_x = jnp.where(lx < 0, -1.0, 1.0).astype(momentum.dtype)
    p_cos = jnp.where(right, st + ly, jnp.abs(lx))
    p_sin = jnp.where(right, lx, sign_x * (st - ly))
    p_norm = safe_norm_of(p_cos, p_sin)
    p_cos = jnp.where(p_norm > 0, p_cos, 1.0)
    p_norm = jnp.where(p_norm > 0, p_norm, 1.0)
    return t_cos / t_norm, t_sin / t_norm, p_cos / p_norm, p_sin / p_norm


def _nutation_spin_quat(momentum):
    """``Rx(theta) Rz(psi)`` as a quaternion (it turns ``momentum`` onto ``+z``), ``psi`` in (-pi, pi]."""
    ct, st, cp, sp = _half_angles(momentum)
    return jnp.stack([ct * cp, st * cp, -st * sp, ct * sp], axis=-1)


def _general_orientation(frame, parts, t):
    """``q0* q(t)`` for a body that is not in steady rotation (see :func:`torque_free_motion`) and
    its precession angle ``phi(t)``."""
    moments, index = frame["moments"], frame["index"]
    around_largest, m, p, nu, u = (parts[k] for k in ("around_largest", "m", "p", "nu", "u"))
    I_a = jnp.where(around_largest, moments[0], moments[2])
    I_b = moments[1]
    I_c = jnp.where(around_largest, moments[2], moments[0])
    n = _clip(_safe_div(I_c * (I_b - I_a), I_a * (I_c - I_b)), 0.0, jnp.inf)

    # The precession angle phi = (|L| / I_c) (t + (I_c - I_a) / I_a (G(tau) - G(tau0)) / (dtau/dt)) with
    # G = g tau + c V: the linear part is a rate, and (|L| / I_c) ((I_c - I_a) / I_a) c / (dtau/dt) = +-1
    # (an identity of the elliptic parameters), so V enters as it is. What depends on the body only
    # (K, g, the initial phase) keeps the body's shape: computed once per body, not per sample time.
    body = _precession_parts(m, p, n, nu, parts["start"])
    size = safe_norm_of(*(i * w for i, w in zip(moments, frame["omega"], strict=True)))
    kappa = jnp.where((I_c > I_a) == (parts["speed"] > 0), 1.0, -1.0).astype(u.dtype)
    # (|L| / I_c) (1 + (I_c - I_a) / I_a g) as |L| (g / I_a + (1 - g) / I_c), with 1 - g formed
    # directly: for a thin rod circling its long axis (I_c << I_a, g -> 1) the first form cancels,
    # an absolute error of eps |L| / I_c in the rate (4e-7 rad in 40 s for I_c / I_a = 1e-9).
    rate = size * (body["slope"] / I_a + body["rest"] / I_c)
    phase0 = _precession_phase(body["rho0"], jnp.zeros_like(body["rho0"]), body)

    # Cyclic relabelling of the body axes: (x, y, c) = (c + 1, c + 2, c) mod 3, a proper rotation; (x, y)
    # is (a, b) (eps = -1) or (b, a) (eps = +1).
    c_index = jnp.where(around_largest, index[2], index[0])
    a_index = jnp.where(around_largest, index[0], index[2])
    eps = jnp.where((c_index + 1) % 3 == a_index, -1.0, 1.0).astype(u.dtype)
    w_a0, w_b0, w_c0 = parts["omega_start"]
    l_a0, l_b0, l_c0 = I_a * w_a0, I_b * w_b0, I_c * w_c0
    x0, y0 = jnp.where(eps < 0, l_a0, l_b0), jnp.where(eps < 0, l_b0, l_a0)
    b0 = _nutation_spin_quat(jnp.stack([x0, y0, l_c0], axis=-1))
    sign0 = jnp.where(parts["start"][1] < 0, -1.0, 1.0).astype(u.dtype)
    beta0 = _rough_angle(sign0 * l_b0, sign0 * l_a0)
    angle0 = _rough_angle(x0, y0)
    # What the samples read of the body, in memory: fused into the per-sample code, which reads it
    # broadcast against t, it would be recomputed for every sample.
    phase_keys = ("upper", "agm", "nome2", "l_safe", "b", "quarter", "rho0")
    per_body = (
        *(body[k] for k in phase_keys), *body["bend"], *body["lower"], rate, phase0, kappa, I_a, I_b, I_c,
        eps, sign0, beta0, angle0, *(b0[..., k] for k in range(4)), c_index,
    )  # fmt: skip
    # (Not held with one sample a body: there every reader computes them once anyway, and holding
    # 28 arrays cost ~0.5 ms for 10^4 bodies' omega and q at one time.)
    per_body = list(_held_per_body(per_body, t))
    body = dict(zip(phase_keys, per_body[:7], strict=True))
    body["bend"], body["lower"] = tuple(per_body[7:10]), tuple(per_body[10:13])
    rate, phase0, kappa, I_a, I_b, I_c, eps, sign0, beta0, angle0 = per_body[13:23]
    b0, c_index = jnp.stack(per_body[23:27], axis=-1), per_body[27]

    # The precession angle phi = (|L| / I_c) (t + (I_c - I_a) / I_a (G(tau) - G(tau0)) / (dtau/dt)) with
    # G = g tau + c V: the linear part is a rate, and (|L| / I_c) ((I_c - I_a) / I_a) c / (dtau/dt) = +-1
    # (an identity of the elliptic parameters), so V enters as it is. What depends on the body only
    # (K, g, the initial phase) keeps the body's shape: computed once per body, not per sample time.
    turns, rho1 = _reduce(body["rho0"] + u, body["quarter"])
    phi = rate * t + kappa * (_precession_phase(rho1, turns, body) - phase0)
    w_a1, w_b1, w_c1 = parts["omega_now"]
    l_a1, l_b1, l_c1 = I_a * w_a1, I_b * w_b1, I_c * w_c1
    x1, y1 = jnp.where(eps < 0, l_a1, l_b1), jnp.where(eps < 0, l_b1, l_a1)
    half_angles1 = _half_angles(jnp.stack(jnp.broadcast_arrays(x1, y1, l_c1), axis=-1))

    # psi = atan2(l_x, l_y) is continuous in t; the quaternions hold its principal value, and each wrap
    # flips the sign of the half-angle quaternion. psi = eps beta + const with beta the angle of
    # (l_a, l_b) ~ (cn, sn), which turns by pi per half period: at the reduced phases (cn >= 0) beta is in
    # [-pi/2, pi/2], so its continuous change is beta(rho1) - beta(rho0) + pi j exactly, and rough
    # angles (errors of 0.005 rad) count the wraps.
    sign1 = sign0 * (1 - 2 * _mod(turns, 2))
    beta1 = _rough_angle(sign1 * l_b1, sign1 * l_a1)
    turned = eps * (beta1 - beta0 + jnp.pi * turns)
    wraps = jnp.round((turned - (_rough_angle(x1, y1) - angle0)) / (2 * jnp.pi))
    flip = jnp.where(_mod(wraps, 2) == 0, 1.0, -1.0).astype(u.dtype)

    (phi,) = _materialised((phi,))  # read by sin and cos, each in a kernel of its own
    sin_p, cos_p = _sin_cos(phi / 2)
    # Every component of q reads all of these: in memory, the products below are cheap.
    sin_p, cos_p, flip, ct, st, cp, sp = _materialised((sin_p, cos_p, flip, *half_angles1))
    b1 = jnp.stack([ct * cp, st * cp, -st * sp, ct * sp], axis=-1)
    zero = jnp.zeros_like(phi)
    precession = jnp.stack([cos_p, zero, zero, sin_p], axis=-1)
    b0_conj = b0 * jnp.array([1.0, -1.0, -1.0, -1.0], u.dtype)
    q = _quat_multiply(b0_conj, _quat_multiply(precession, b1)) * flip[..., None]
    vector = _cycle([q[..., 1], q[..., 2], q[..., 3]], (2 - c_index) % 3)
    return jnp.stack([q[..., 0], *vector], axis=-1), phi
