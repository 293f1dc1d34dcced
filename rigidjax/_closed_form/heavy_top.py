"""Lagrange's top in closed form: a heavy symmetric top (``I1 = I2`` about the pivot, centre of
mass on the body z axis) under gravity along space -Z.

Classical solution (Goldstein, Classical Mechanics, section 5.7; Whittaker, Analytical Dynamics,
section 71) in a form that never goes through the 3-1-3 angles themselves. With ``A = I1``,
``C = I3``, ``a = C w3 / A``, ``b = L_z / A`` and ``beta = 2 m g l / A``, ``u = cos theta`` obeys
``du/dt^2 = f(u) = (1 - u^2)(alpha - beta u) - (b - a u)^2``, a cubic. Its coefficients are taken about
the initial ``u0`` from body-frame quantities (``f(u0) = (e1 w2 - e2 w1)^2`` with ``e`` the body-frame
vertical), so that nothing cancels for a fast top whose nutation is tiny. Factoring
``f(u0 + x) = -(x - x1)(x - x2) g(u0 + x)`` with ``g`` linear and positive on the motion,
``g(u0)`` is the largest root of a monic resolvent cubic that stays regular as ``beta -> 0``, and
``x1 <= 0 <= x2`` (the turning circles) come from a quadratic whose discriminant is the nutation
amplitude ``u2 - u1`` itself. Then ``u = u_s + sigma (u2 - u1) sn^2(lambda t + tau0 | m)``, expanded about
the lower turning circle for a standing top and the upper one for a hanging top, so that
``0 <= m < 1`` for either sign of ``l``; ``tau0`` enters by the addition theorem, as in
:mod:`.torque_free`.

The orientation is built from its Cayley-Klein halves ``w + i z = cos(theta/2) e^{i(phi + psi)/2}``
and ``x + i y = sin(theta/2) e^{i(phi - psi)/2}``: their moduli are ``sqrt((1 +- u)/2)`` and their phases
obey ``d(phi + k psi)/dt = k (w3 - a) + (b + k a) / (1 + k u)`` (``k = +-1``), whose integrals are
Carlson ``R_F``/``R_J`` forms of the third kind, each singular only at its own pole (``u = -k``). A
half whose pole is a turning point (a top started exactly upright, or swinging through the
vertical) has ``b + k a = 0``: there the half is a signed Jacobi function times a uniformly
rotating phase, smooth through the pole, where the 3-1-3 angles lock and jump by pi. The
body-frame ``omega`` follows from ``(w1 + i w2) = (i/2)(h + i du/dt) / (conj(x + i y)(w + i z))``,
``h = b - a u``, written so that it stays finite at either pole.

Accuracy (``tests/test_heavy_top_exact.py``, against DOP853 at rtol 1e-13 over 10 or more nutation
periods): ``omega`` within 4e-11 of ``max |omega|`` and ``q`` within 4e-11 in every regime tested (fast,
cusped, looping, hanging, sleeping at theta = 0 and 1e-5, falling through the vertical, steady
precession, ``l = 0``); 1.4e-10 for a very slow top over 2e4 s. float32: ``q`` within 2e-5 over
20 s (1.4e-4 for a looping top, 8e-5 for a fast top at ``|omega| t = 1600`` rad).

Derivatives (forward and reverse) are those of the motion, including a start on a turning circle
(a top released with ``theta' = 0``), tops passing close to the vertical and steady precession
(a nutation below ``eps^(2/3)`` is evaluated in its first-order form, which carries them) and a
top sleeping exactly at a pole (the linearised tilt, two circular modes). A top started exactly at
a pole with a finite wobble (``theta0 = 0``, ``omega0`` not along the axis) has exact values and
finite derivatives, but the derivative with respect to the tilt of ``q0`` is not the motion's.
Only ``com_z`` and the mean of ``I1`` and ``I2`` enter, so the derivatives with respect to
``com_x``, ``com_y`` (zero) and ``I1 - I2`` are not the motion's (they leave Lagrange's case)."""

import jax
import jax.numpy as jnp

from .._numerics import safe_norm
from .carlson import _carlson_rf_rj
from .elliptic import _ellipj_checked, _sin_cos


def _safe_div(num, den):
    ok = den != 0
    return jnp.where(ok, num / jnp.where(ok, den, 1.0), 0.0)


def _safe_sqrt(x):
    """``sqrt(max(x, 0))`` with a zero (not infinite) derivative at 0."""
    ok = x > 0
    return jnp.where(ok, jnp.sqrt(jnp.where(ok, x, 1.0)), 0.0)


def _times(x, z):
    """A real ``x`` times a complex ``z`` (explicit: no real/complex promotion)."""
    return jax.lax.complex(x * jnp.real(z), x * jnp.imag(z))


def _unit(z):
    """``z / |z|`` for a complex ``z``, 1 at ``z = 0`` (finite derivative there)."""
    r2 = jnp.real(z) ** 2 + jnp.imag(z) ** 2
    ok = r2 > 0
    return jnp.where(ok, _times(1 / jnp.sqrt(jnp.where(ok, r2, 1.0)), z), jnp.ones_like(z))


def _largest_root(c2, c1, c0):
    """Largest root of ``G^3 + c2 G^2 + c1 G + c0`` whose roots are all real.

    The trigonometric formula gives all three roots of the scaled cubic, but a root in a close pair
    only to ~sqrt(eps) (a near-sleeping top: two roots 1e-11 apart next to one at -4). So only the
    most isolated root, which is well conditioned, is kept (polished by Newton steps); the other two
    come from the deflated quadratic by the stable formula. All without derivatives; then one
    Newton step on the original coefficients with them: the implicit-function derivative
    ``-dh / h'(G)`` of a simple root.
    """
    dtype = c2.dtype
    scale = jnp.abs(c2) + jnp.sqrt(jnp.abs(c1)) + jnp.cbrt(jnp.abs(c0))
    scale = jax.lax.stop_gradient(jnp.where(scale > 0, scale, 1.0))  # a unit only: no derivative
    s2, s1, s0 = (jax.lax.stop_gradient(c) for c in (c2 / scale, c1 / scale**2, c0 / scale**3))
    p = s1 - s2 * s2 / 3
    q = 2 * s2**3 / 27 - s2 * s1 / 3 + s0
    r = _safe_sqrt(-p / 3)
    angle = jnp.arccos(jnp.clip(_safe_div(-q, 2 * r**3), -1.0, 1.0)) / 3
    roots = [2 * r * jnp.cos(angle - 2 * jnp.pi * k / 3) - s2 / 3 for k in range(3)]
    roots[0] = jnp.where(r > 0, roots[0], jnp.cbrt(-q) - s2 / 3)
    gaps = [jnp.minimum(jnp.abs(roots[k] - roots[k - 1]), jnp.abs(roots[k] - roots[k - 2])) for k in range(3)]
    lone = jnp.where(
        gaps[0] >= jnp.maximum(gaps[1], gaps[2]), roots[0], jnp.where(gaps[1] >= gaps[2], roots[1], roots[2])
    )

    def newton(g, coeffs):
        a2, a1, a0 = coeffs
        value = ((g + a2) * g + a1) * g + a0
        slope = (3 * g + 2 * a2) * g + a1
        return g - _safe_div(value, slope)

    for _ in range(2):
        g_new = newton(lone, (s2, s1, s0))
        lone = jnp.where(jnp.isfinite(g_new), g_new, lone)
    # (G - lone)(G^2 + B G + C): B = s2 + lone, C = -s0 / lone (or s1 + lone B when lone = 0).
    B = s2 + lone
    C = jnp.where(lone != 0, -_safe_div(s0, lone), s1 + lone * B)
    root_disc = _safe_sqrt(B * B - 4 * C)
    big = -(B + jnp.where(B >= 0, root_disc, -root_disc)) / 2
    pair_max = jnp.maximum(big, _safe_div(C, big))
    pair_max = jnp.where(big != 0, pair_max, 0.0)
    g = jax.lax.stop_gradient(jnp.maximum(lone, pair_max)) * scale
    return newton(g, (c2, c1, c0)).astype(dtype)


def _third_kind(sn, cn, dn, m, p, n, n1, quarter=None):
    """Reduced phase ``rho`` and ``G(rho) = int_0^rho dtau / (1 + n sn^2)`` of the point ``(sn, cn, dn)``.

    The point fixes ``tau = rho + 2 j K`` (``|rho| <= K``); ``G(tau) = G(rho) + 2 j G(K)``. ``n1 = 1 + n``
    is passed on its own (``n > -1``). Carlson forms (DLMF 19.25.5, 19.25.14) for ``sn^2 <= 1/2``, else
    measured back from ``K`` so that the arguments stay accurate as ``p = 1 - m -> 0`` (the same
    construction as in :mod:`.torque_free`). Near the pole (``n1 < 1/2``, a turning circle close to
    the vertical) ``R_J``'s last argument would grow like ``1 / n1``; there the characteristic
    ``N = -n`` is exchanged for ``N' = m / N`` (DLMF 19.7.9), which leaves the near-singular part as
    an arctangent: ``G = -(N'/3) s^3 R_J(c^2, dn^2, 1, 1 - N' s^2) + atan2(s r, c dn) / r`` with
    ``r = sqrt(n1 (1 - N'))``. Returns ``rho``, ``G(rho)`` and ``quarter = (K, G(K))``.
    """
    c, s = jnp.abs(cn), jnp.abs(sn)
    sign_s = jnp.where(sn < 0, -1.0, 1.0).astype(sn.dtype)
    sign_c = jnp.where(cn < 0, -1.0, 1.0).astype(sn.dtype)
    direct = s * s <= 0.5
    pc = jnp.where(p > 0, p, jnp.ones_like(p))
    big_n = -n
    # N' = m / N < 1 needs p > n1; 1 - N' = (p - n1) / N and 1 - N' sn^2 = (dn^2 - n1) / N are
    # formed from p and n1, which are accurate on their own.
    near_pole = (n1 < 0.5) & (2 * n1 < p)
    big_n = jnp.where(near_pole, big_n, 1.0)
    swapped = jnp.where(near_pole, m / big_n, 0.0)  # N'
    r = _safe_sqrt(n1 * (p - n1) / big_n)
    r = jnp.where(r > 0, r, 1.0)
    pole = c * c + n1 * s * s  # 1 + n sn^2 as a sum of nonnegative terms
    plain = direct | near_pole
    args = (
        jnp.where(plain, c * c, pc * s * s),
        dn * dn,
        jnp.where(plain, jnp.ones_like(s), pc),
        jnp.where(near_pole, (dn * dn - n1) / big_n, jnp.where(direct, pole, pc * pole / n1)),
    )
    weight = n / n1 * pc / 3
    if quarter is None:
        last = jnp.where(near_pole, (p - n1) / big_n, pc / n1)
        extra = (jnp.zeros_like(pc), jnp.ones_like(pc), pc, last)
        rf, rj = _carlson_rf_rj(
            *(jnp.stack(jnp.broadcast_arrays(x, y)) for x, y in zip(args, extra, strict=True))
        )
        quarter_g = jnp.where(
            near_pole, -(swapped / 3) * rj[1] + (jnp.pi / 2) / r, (rf[1] + weight * rj[1]) / n1
        )
        quarter = rf[1], quarter_g
        rf, rj = rf[0], rj[0]
    else:
        rf, rj = _carlson_rf_rj(*args)
    quarter_f, quarter_g = quarter
    f = sign_s * jnp.where(plain, s * rf, quarter_f - c * rf)
    g_pole = -(swapped / 3) * s**3 * rj + jnp.arctan2(s * r, c * dn) / r
    g_plain = jnp.where(direct, s * rf - (n / 3) * s**3 * rj, quarter_g - (c * rf + weight * c**3 * rj) / n1)
    g = sign_s * jnp.where(near_pole, g_pole, g_plain)
    return sign_c * f, sign_c * g, quarter


def _body(A, C, weight_l, omega0, q0):
    """Everything that depends on the body only (not on time): roots, elliptic parameters, phases."""
    dtype = omega0.dtype
    q0 = q0 / safe_norm(q0, keepdims=True)
    w, x, y, z = (q0[..., i] for i in range(4))
    w1, w2, w3 = omega0[..., 0], omega0[..., 1], omega0[..., 2]
    # e: the space vertical in body components (third row of R).
    e1, e2 = 2 * (x * z - w * y), 2 * (y * z + w * x)
    up, down = w * w + z * z, x * x + y * y  # (1 + u0) / 2 and (1 - u0) / 2, without cancellation
    u0 = up - down
    a = C * w3 / A
    beta = 2 * weight_l / A
    perp2 = w1 * w1 + w2 * w2  # alpha - beta u0
    h = w1 * e1 + w2 * e2  # b - a u0
    sin2 = 4 * up * down  # 1 - u0^2
    udot = e1 * w2 - e2 * w1
    # f(u0 + x) = f0 + f1 x + f2 x^2 + beta x^3.
    f0 = udot * udot
    f1 = 2 * a * h - 2 * u0 * perp2 - beta * sin2
    f2 = 2 * u0 * beta - perp2 - a * a
    # f(u0 + x) = -(x^2 + k1 x + k0) (G0 - beta x), G0 = g(u0) > 0 the largest root of the resolvent.
    g0 = _largest_root(f2, beta * f1, beta * beta * f0)
    k0 = -_safe_div(f0, g0)
    k1 = -_safe_div(f1 + beta * _safe_div(f0, g0), g0)
    amp = _safe_sqrt(k1 * k1 - 4 * k0)  # u2 - u1
    big = -(k1 + jnp.where(k1 >= 0, amp, -amp)) / 2
    small = _safe_div(k0, big)
    x1 = jnp.where(k1 >= 0, big, small)
    x2 = jnp.where(k1 >= 0, small, big)
    x1, x2 = jnp.minimum(x1, 0.0), jnp.maximum(x2, 0.0)
    standing = beta >= 0
    sigma = jnp.where(standing, 1.0, -1.0).astype(dtype)
    x_s = jnp.where(standing, x1, x2)  # the turning circle the expansion starts from
    x_o = jnp.where(standing, x2, x1)
    g_s = g0 - beta * x_s
    g_o = g0 - beta * x_o
    rate = _safe_sqrt(g_s) / 2  # lambda
    m = _safe_div(jnp.abs(beta) * amp, g_s)
    p = jnp.where(g_s > 0, jnp.maximum(_safe_div(g_o, g_s), 0.0), 1.0)
    # sn0^2 = |x_s| / amp, cn0^2 = |x_o| / amp, sign(sn0 cn0) = sigma sign(du/dt). The smaller of the
    # two is formed from |x_s x_o| = (du/dt)^2 / G0 with the sign of du/dt: smooth through a start on
    # a turning circle (a top released with theta' = 0), where its square root alone is not.
    moving = amp > 0
    at_start = jnp.abs(x_s) <= jnp.abs(x_o)
    larger = jnp.where(at_start, jnp.abs(x_o), jnp.abs(x_s))
    root_large = _safe_sqrt(_safe_div(larger, amp))
    root_small = sigma * _safe_div(udot, _safe_sqrt(g0 * larger * amp))
    sn0 = jnp.where(moving, jnp.where(at_start, root_small, root_large), 0.0)
    cn0 = jnp.where(moving, jnp.where(at_start, root_large, root_small), 1.0)
    dn0 = jnp.where(g_s > 0, _safe_sqrt(_safe_div(g0, g_s)), 1.0)
    # The time derivative of q0 (for the phase of a half that starts at its pole).
    qdot0 = _quat_times_omega(q0, omega0)
    halves = []
    for k, z0, zdot0, dist0 in (
        (1.0, jax.lax.complex(w, z), jax.lax.complex(qdot0[..., 0], qdot0[..., 3]), 2 * up),
        (-1.0, jax.lax.complex(x, y), jax.lax.complex(qdot0[..., 1], qdot0[..., 2]), 2 * down),
    ):
        coeff = h + k * a * dist0  # b + k a
        near = dist0 + k * x_s  # 1 + k u at the start circle (P) and at the other (P')
        far = dist0 + k * x_o
        near, far = jnp.maximum(near, 0.0), jnp.maximum(far, 0.0)
        # b + k a = 0 puts the pole on a root of f: a turning circle (reached) or the third root.
        third = jnp.abs(dist0 * beta + k * g0)  # |beta (1 + k u3)|
        reached = (coeff == 0) & (jnp.minimum(near, far) * jnp.abs(beta) < third)
        halves.append(
            dict(k=k, z0=z0, zdot0=zdot0, coeff=coeff, near=near, far=far, reached=reached, dist0=dist0)
        )
    return dict(
        a=a, w3=w3, h0=h, u0=u0, udot0=udot, amp=amp, sigma=sigma, rate=rate, m=m, p=p,
        start=(sn0, cn0, dn0), halves=halves, k1=k1, g0=g0, beta=beta, w1=w1, w2=w2,
        pole_gap=2 * jnp.minimum(up, down),
    )  # fmt: skip


def _quat_times_omega(q, omega):
    """``dq/dt = q (0, omega) / 2``."""
    w, x, y, z = (q[..., i] for i in range(4))
    w1, w2, w3 = omega[..., 0], omega[..., 1], omega[..., 2]
    return 0.5 * jnp.stack(
        [
            -x * w1 - y * w2 - z * w3,
            w * w1 + y * w3 - z * w2,
            w * w2 - x * w3 + z * w1,
            w * w3 + x * w2 - y * w1,
        ],
        axis=-1,
    )


def _half(half, body, t, now, reduced):
    """One Cayley-Klein half at time ``t``: its signed modulus, unit phase and modulus rate."""
    k, coeff, near, far = half["k"], half["coeff"], half["near"], half["far"]
    sn, cn, dn = now
    rate, amp, sigma = body["rate"], body["amp"], body["sigma"]
    spin = k * (body["w3"] - body["a"])
    dist = near * cn * cn + far * sn * sn  # 1 + k u(t), a sum of nonnegative terms
    udot = 2 * sigma * amp * rate * sn * cn * dn
    modulus = _safe_sqrt(dist / 2)
    modulus_rate = _safe_div(k * udot, 4 * modulus)
    # The phase: (1/2) [k (w3 - a) t + (b + k a) int_0^t dt / (1 + k u)].
    p, m = body["p"], body["m"]
    nn = _safe_div(k * sigma * amp, near)
    n1 = jnp.where(near > 0, _safe_div(far, near), 1.0)
    n1 = jnp.where(n1 > 0, n1, 1.0)
    (sn0, cn0, dn0), v = body["start"], reduced
    rho0, g0, quarter = _third_kind(sn0, cn0, dn0, m, p, nn, n1)
    rho1, g1, _ = _third_kind(sn, cn, dn, m, p, nn, n1, quarter)
    turns = jnp.round(_safe_div(v + rho0 - rho1, 2 * quarter[0]))
    delta_g = g1 - g0 + 2 * turns * quarter[1]
    moving = (amp > 0) & (rate > 0)
    integral = jnp.where(moving, _safe_div(delta_g, near * jnp.where(moving, rate, 1.0)), _safe_div(t, near))
    # A nutation below eps^(2/3) (steady precession, up to roundoff): its first-order form, exact in
    # value there (errors O(amp^2)) and with the derivatives of the flow, which the elliptic form's
    # square roots of the amplitude do not give. x(t) = u - u0 solves x'' = -G0 (x + k1 / 2).
    # (Also small against both poles' distances: 1 / (1 + k u) is expanded to first order.)
    linear = (amp <= jnp.finfo(amp.dtype).eps ** (2 / 3) * body["pole_gap"]) & (body["g0"] > 0)
    nu = _safe_sqrt(jnp.where(linear, body["g0"], 1.0))
    k1, udot0, dist0 = body["k1"], body["udot0"], half["dist0"]
    sin_t, cos_t = _sin_cos(nu * t)
    x_lin = -(k1 / 2) * (1 - cos_t) + udot0 * sin_t / nu
    xdot_lin = -(k1 / 2) * nu * sin_t + udot0 * cos_t
    xint_lin = -(k1 / 2) * (t - sin_t / nu) + udot0 * (1 - cos_t) / nu**2
    dist = jnp.where(linear, dist0 + k * x_lin, dist)
    udot = jnp.where(linear, xdot_lin, udot)
    modulus = jnp.where(linear, _safe_sqrt(dist / 2), modulus)
    modulus_rate = jnp.where(linear, _safe_div(k * udot, 4 * modulus), modulus_rate)
    integral = jnp.where(linear, _safe_div(t, dist0) - k * _safe_div(xint_lin, dist0 * dist0), integral)
    regular_coeff = jnp.where(half["reached"], 0.0, coeff)
    phase = 0.5 * (spin * t + regular_coeff * integral)
    sin_phase, cos_phase = _sin_cos(phase)
    rotor = jax.lax.complex(cos_phase, sin_phase)
    regular = (_unit(half["z0"]), modulus, modulus_rate)
    # A pole on a turning circle: the modulus is sqrt(P_far / 2) J(tau) with J = sn when the start
    # circle is the pole (cn otherwise), and the phase turns uniformly.
    start_is_pole = near <= far
    scale = _safe_sqrt(jnp.maximum(near, far) / 2)
    j_now = jnp.where(start_is_pole, sn, cn)
    jdot_now = jnp.where(start_is_pole, cn * dn, -sn * dn)
    j0 = jnp.where(start_is_pole, sn0, cn0)
    jdot0 = jnp.where(start_is_pole, cn0 * dn0, -sn0 * dn0)
    # q0's half is Z (scale J0) and its rate Z (scale (lambda J0' + i spin J0 / 2)): a positive
    # multiple of the unit phase Z is  z0 J0 + (zdot0 - i spin z0 / 2) J0' / lambda.
    z0, zdot0 = half["z0"], half["zdot0"]
    drift = zdot0 - _times(spin / 2, jax.lax.complex(-jnp.imag(z0), jnp.real(z0)))  # zdot0 - i spin z0 / 2
    direction = _unit(_times(j0, z0) + _times(_safe_div(1.0, rate) * jdot0, drift))
    pole = (direction, scale * j_now, scale * jdot_now * rate)
    chosen = [jnp.where(half["reached"], x, y) for x, y in zip(pole, regular, strict=True)]
    return chosen[0] * rotor, chosen[1], chosen[2], udot


def lagrange_top_motion(inertia, mass, com, gravity, omega0, q0, t):
    """Body-frame ``omega(t)`` and orientation ``q(t)`` of Lagrange's top, in closed form.

    **Arguments:**

    - `inertia`: principal moments about the pivot ``(..., 3)`` with ``I1 = I2`` (their mean is
      used, so a derivative with respect to ``I1`` and ``I2`` is split between them).
    - `mass`, `gravity`: ``(...)``; `com`: ``(..., 3)`` on the body z axis (only ``com_z`` is used).
    - `omega0`: body-frame angular velocity at ``t = 0`` ``(..., 3)``; `q0`: unit quaternion ``(..., 4)``.
    - `t`: times ``(..., T)`` or anything that broadcasts against the bodies' batch axes.

    **Returns:** ``(omega, q)``: the body-frame angular velocity (rad/s), shape ``batch + (3,)``, and
    the unit quaternion ``(w, x, y, z)`` (body to space), shape ``batch + (4,)``; ``batch`` is the
    broadcast of the bodies' batch axes with ``t``'s shape. The inputs are not checked here:
    ``simulate`` checks them (a physical inertia, ``I1 = I2``, ``com`` on the z axis, a unit ``q0``).
    """
    A = 0.5 * (inertia[..., 0] + inertia[..., 1])
    C = inertia[..., 2]
    body = _body(A, C, mass * gravity * com[..., 2], omega0, q0)
    sn0, cn0, dn0 = body["start"]
    v = body["rate"] * t
    sn_v, cn_v, dn_v, _ = _ellipj_checked(v, body["m"], body["p"])
    m = body["m"]
    # Addition theorem, written without cancellation where sn and sn0 are both near 1.
    den = cn0 * cn0 + sn0 * sn0 * dn_v * dn_v
    sn = (sn_v * cn0 * dn0 + sn0 * cn_v * dn_v) / den
    cn = (cn_v * cn0 - sn_v * sn0 * dn_v * dn0) / den
    dn = (dn_v * dn0 - m * sn_v * sn0 * cn_v * cn0) / den
    now = (sn, cn, dn)
    (ph_p, mod_p, rate_p, udot), (ph_m, mod_m, rate_m, _) = (
        _half(half, body, t, now, v) for half in body["halves"]
    )
    q = jnp.stack(
        [mod_p * jnp.real(ph_p), mod_m * jnp.real(ph_m), mod_m * jnp.imag(ph_m), mod_p * jnp.imag(ph_p)],
        axis=-1,
    )
    # omega_1 + i omega_2 = (i/2)(h + i du/dt) / (A_- A_+) * E_- conj(E_+); at a reached pole the
    # ratio (h + i du/dt) / A_pole is taken from its limit form.
    a = body["a"]
    up_pole, down_pole = body["halves"][0]["reached"], body["halves"][1]["reached"]
    # h = b - a u from the pole the top is nearer: (b - a) + a (1 - u) or (b + a) - a (1 + u).
    dist_m, dist_p = 2 * mod_m * mod_m, 2 * mod_p * mod_p
    h = jnp.where(
        dist_m <= dist_p, body["halves"][1]["coeff"] + a * dist_m, body["halves"][0]["coeff"] - a * dist_p
    )
    regular = _times(_safe_div(1.0, mod_m * mod_p), jax.lax.complex(h, udot))
    at_down = _times(_safe_div(1.0, mod_p), jax.lax.complex(2 * a * mod_m, -4 * rate_m))
    at_up = _times(_safe_div(1.0, mod_m), jax.lax.complex(-2 * a * mod_p, 4 * rate_p))
    ratio = jnp.where(down_pole, at_down, jnp.where(up_pole, at_up, regular))
    transverse = ratio * ph_m * jnp.conj(ph_p)
    transverse = jax.lax.complex(-jnp.imag(transverse) / 2, jnp.real(transverse) / 2)  # times i/2
    # A top sleeping at a pole up to a wobble below eps^(2/3): the linearised motion, zero in value
    # at the equilibrium and carrying the derivatives that start a wobble (the pole form's direction
    # of the wobble is undefined there). The tilt T = X + iY of the symmetry axis (T = -2i (x+iy)(w+iz))
    # is a sum of circular modes exp(i lambda t), lambda^2 - s a lambda + s beta / 2 = 0, s = +1 upright
    # (T' = -i W^2 Omega), s = -1 hanging straight down (T' = i Z^2 conj(Omega)).
    tiny = body["amp"] <= jnp.finfo(body["amp"].dtype).eps ** (2 / 3)
    halves = body["halves"]
    tilt0 = -2 * _times_i(halves[1]["z0"] * halves[0]["z0"])
    omega0_t = jax.lax.complex(body["w1"], body["w2"])
    rate_up = -_times_i(halves[0]["z0"] ** 2 * omega0_t)
    rate_down = _times_i(halves[1]["z0"] ** 2 * jnp.conj(omega0_t))
    tilt_up, tilt_rate_up = _tilt_modes(1.0, a, body["beta"], tilt0, rate_up, t)
    tilt_down, tilt_rate_down = _tilt_modes(-1.0, a, body["beta"], tilt0, rate_down, t)
    sleep_up, sleep_down = down_pole & tiny, up_pole & tiny & ~down_pole
    zeta = _times_i(tilt_up * jnp.conj(ph_p)) / 2
    big_w = _times_i(tilt_down * jnp.conj(ph_m)) / 2
    q = jnp.where(
        sleep_up[..., None], jnp.stack([q[..., 0], jnp.real(zeta), jnp.imag(zeta), q[..., 3]], -1), q
    )
    q = jnp.where(
        sleep_down[..., None], jnp.stack([jnp.real(big_w), q[..., 1], q[..., 2], jnp.imag(big_w)], -1), q
    )
    transverse = jnp.where(sleep_up, _times_i(tilt_rate_up * jnp.conj(ph_p) ** 2), transverse)
    transverse = jnp.where(sleep_down, _times_i(jnp.conj(tilt_rate_down) * ph_m**2), transverse)
    w3 = jnp.broadcast_to(body["w3"], transverse.shape)
    omega = jnp.stack([jnp.real(transverse), jnp.imag(transverse), w3], axis=-1)
    return omega, q


def _times_i(z):
    return jax.lax.complex(-jnp.imag(z), jnp.real(z))


def _tilt_modes(s, a, beta, tilt0, rate0, t):
    """``T(t)`` and ``T'(t)`` for ``T = c1 exp(i l1 t) + c2 exp(i l2 t)`` with ``T(0)``, ``T'(0)`` given and
    ``l`` the roots of ``l^2 - s a l + s beta / 2 = 0`` (complex below the sleeping threshold)."""
    disc = a * a - 2 * s * beta
    disc = jnp.where(disc != 0, disc, 1.0)  # at the threshold itself the modes merge: not resolved
    root = jnp.sqrt(jax.lax.complex(disc, jnp.zeros_like(disc)))
    sa = jax.lax.complex(s * a, jnp.zeros_like(a))
    l1, l2 = (sa + root) / 2, (sa - root) / 2
    c1 = (rate0 - _times_i(l2 * tilt0)) / _times_i(root)
    c2 = tilt0 - c1
    tc = jax.lax.complex(t, jnp.zeros_like(t))
    e1, e2 = jnp.exp(_times_i(l1 * tc)), jnp.exp(_times_i(l2 * tc))
    return c1 * e1 + c2 * e2, _times_i(l1 * c1 * e1 + l2 * c2 * e2)
