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
elliptic integrals of the third kind, each singular only at its own pole (``u = -k``), evaluated in
Jacobi's theta form (:mod:`.heavy_phase`): a rate and a theta product's phase, whose coefficients are
computed once per body, so that a sample costs one Jacobi triple and two such phases. A
half whose pole is a turning point (a top started exactly upright, or swinging through the
vertical) has ``b + k a = 0``: there the half is a signed Jacobi function times a uniformly
rotating phase, smooth through the pole, where the 3-1-3 angles lock and jump by pi. The
body-frame ``omega`` follows from ``(w1 + i w2) = (i/2)(h + i du/dt) / (conj(x + i y)(w + i z))``,
``h = b - a u``, written so that it stays finite at either pole.

Accuracy (``tests/test_heavy_top_exact.py``, against DOP853 at rtol 1e-13 over 10 or more nutation
periods): ``omega`` within 4e-11 of ``max |omega|`` and ``q`` within 4e-11 in every regime tested (fast,
cusped, looping, hanging, sleeping at theta = 0 and 1e-5, falling through the vertical, steady
precession, ``l = 0``); 1.4e-10 for a very slow top over 2e4 s. Next to the heavy top's separatrix
(a top rising towards upright for ever: a double root of ``f`` at the pole) ``omega`` within 5e-8,
the double root being known from the cubic's coefficients to about ``sqrt(eps)``. float32: ``q``
within 2e-5 over 20 s (1.4e-4 for a looping top, 8e-5 for a fast top at ``|omega| t = 1600`` rad).

Derivatives (forward and reverse) are those of the motion, including a start on a turning circle
(a top released with ``theta' = 0``), tops passing close to the vertical and steady precession
(a nutation below ``eps^(2/3)`` is evaluated in its first-order form, which carries them) and a
top exactly at a pole without a wobble (the linearised tilt: two circular modes above the sleeping
threshold, a growing and a decaying one below it and at rest upright). A half with ``b + k a = 0``
(a top with ``w3 = 0`` and ``L_z = 0``, released from rest or swinging in a vertical plane through
the pivot; a top started exactly at a pole, whose tilt moves ``b + k a`` off 0) takes the terms that
carry the derivative of ``b + k a`` from :mod:`.heavy_pole`: against central differences of DOP853
(``tests/test_heavy_top_rest_gradients.py``: at rest at a tilt, planar swings below and over the
top, hanging at rest, started upright or hanging with a wobble) the Jacobian with respect to
``omega0`` and the tilt of ``q0`` is within 4e-9 of its largest entry. Those terms are held constant
under differentiation, so second derivatives there lack their part. A top in that family up to
rounding is taken as in it in value, keeping its derivatives: ``b + k a`` within the rounding of
its terms (``8 eps (|omega_perp| + |a| (1 + k u0))``; a planar swing whose ``q0`` comes from Euler angles has
1e-16 rad/s) as 0, and a half of ``q0`` below ``eps`` (``quat_from_euler((0, pi, 0))``) as 0. A
top farther off, yet close to it, takes the general form, whose derivative after a pass by the pole
is off by up to about ``1e-15 / |b + k a|`` relative (a planar swing over 1.3 s: 2e-3 at 4e-13,
3e-8 at 4e-9 rad/s). Reverse mode transposes every sample's Jacobian (:mod:`.derivatives`). Only
``com_z`` and the mean of ``I1`` and ``I2`` enter, so the derivatives with respect to ``com_x``,
``com_y`` (zero) and ``I1 - I2`` are not the motion's (they leave Lagrange's case)."""

import jax
import jax.numpy as jnp

from .._numerics import safe_norm, safe_sqrt
from .barrier import _materialised
from .derivatives import sample_jacobians
from .elliptic import _ellipj_checked, _sin_cos
from .frame import largest_phase
from .heavy_phase import _quarter_period, _start_phase, _theta_parts, _theta_phase
from .heavy_pole import epsilon_step, pole_root_terms, taken_as_zero


def _safe_div(num, den):
    ok = den != 0
    return jnp.where(ok, num / jnp.where(ok, den, 1.0), 0.0)


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
    r = safe_sqrt(-p / 3)
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
    # (G - lone)(G^2 + B G + C): C = -s0 / lone (or s1 + lone B when lone = 0), and B = s2 + lone or
    # B = (C - s1) / lone, whichever cancels less (the first where lone^2 < |C|): a pair far closer to each
    # other's negative than to lone (a top released at rest 1e-8 rad from upright, its roots 0, ~1e-16
    # and -4) keeps its sum only in the second.
    vieta_sum = s2 + lone
    C = jnp.where(lone != 0, -_safe_div(s0, lone), s1 + lone * vieta_sum)
    B = jnp.where(lone * lone >= jnp.abs(C), _safe_div(C - s1, lone), vieta_sum)
    root_disc = safe_sqrt(B * B - 4 * C)
    big = -(B + jnp.where(B >= 0, root_disc, -root_disc)) / 2
    pair_max = jnp.maximum(big, _safe_div(C, big))
    pair_max = jnp.where(big != 0, pair_max, 0.0)
    g = jax.lax.stop_gradient(jnp.maximum(lone, pair_max)) * scale
    # At a root of a close pair (a top next to its separatrix) the slope vanishes: the step, meant to
    # move the value by its rounding only, would throw it off the root (22.5 -> 13.8).
    polished = newton(g, (c2, c1, c0))
    rounding = jnp.sqrt(jnp.finfo(dtype).eps)  # far above a step's rounding, far below a throw
    moved = jax.lax.stop_gradient(jnp.abs(polished - g) > rounding * jnp.abs(g))
    # There the value stays the pair's root, the derivative the step's (-dh / h'), as elsewhere.
    return jnp.where(moved, g + (polished - jax.lax.stop_gradient(polished)), polished).astype(dtype)


def _body(A, C, weight_l, omega0, q0):
    """Everything that depends on the body only (not on time): roots, elliptic parameters, phases."""
    dtype = omega0.dtype
    q0 = q0 / safe_norm(q0, keepdims=True)
    w, x, y, z = (q0[..., i] for i in range(4))
    # A top at a pole up to the rounding of q0 (a half below eps, as from quat_from_euler((0, pi, 0)))
    # takes the pole's form, whose derivatives are the motion's (the general form's are not there).
    eps = jnp.finfo(q0.dtype).eps
    up_tiny, down_tiny = w * w + z * z <= eps**2, x * x + y * y <= eps**2
    w, z = taken_as_zero(w, up_tiny), taken_as_zero(z, up_tiny)
    x, y = taken_as_zero(x, down_tiny), taken_as_zero(y, down_tiny)
    q0 = jnp.stack([w, x, y, z], axis=-1)
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
    f0 = udot * udot  # f(u0 + x) = f0 + f1 x + f2 x^2 + beta x^3
    f1 = 2 * a * h - 2 * u0 * perp2 - beta * sin2
    f2 = 2 * u0 * beta - perp2 - a * a
    # f(u0 + x) = -(x^2 + k1 x + k0) (G0 - beta x), G0 = g(u0) > 0 the largest root of the resolvent.
    g0 = _largest_root(f2, beta * f1, beta * beta * f0)
    k0 = -_safe_div(f0, g0)
    k1 = -_safe_div(f1 + beta * _safe_div(f0, g0), g0)
    amp = safe_sqrt(k1 * k1 - 4 * k0)  # u2 - u1
    big = -(k1 + jnp.where(k1 >= 0, amp, -amp)) / 2
    small = _safe_div(k0, big)
    x1 = jnp.where(k1 >= 0, big, small)
    x2 = jnp.where(k1 >= 0, small, big)
    x1, x2 = jnp.minimum(x1, 0.0), jnp.maximum(x2, 0.0)
    standing = beta >= 0
    sigma = jnp.where(standing, 1.0, -1.0).astype(dtype)
    x_s = jnp.where(standing, x1, x2)  # the turning circle the expansion starts from
    x_o = jnp.where(standing, x2, x1)
    # The two halves (k = +1: w + iz, pole u = -1; k = -1: x + iy, pole u = 1) on a leading axis of
    # every array: their arithmetic is written, traced and compiled once.
    batch = jnp.broadcast_shapes(u0.shape, a.shape, beta.shape, g0.shape)
    k = jnp.asarray([1.0, -1.0], dtype).reshape((2,) + (1,) * len(batch))

    def pair(plus, minus):
        return jnp.stack([jnp.broadcast_to(plus, batch), jnp.broadcast_to(minus, batch)])

    dist0 = pair(2 * up, 2 * down)
    coeff = h + k * a * dist0  # b + k a
    # Within its terms' rounding (a planar swing's q0 from Euler angles: 1e-16 rad/s) it is taken as 0.
    coeff = taken_as_zero(coeff, jnp.abs(coeff) <= 8 * eps * (safe_sqrt(perp2) + jnp.abs(a) * dist0))
    near = dist0 + k * x_s  # 1 + k u at the start circle (P) and at the other (P')
    far = dist0 + k * x_o
    near, far = jnp.maximum(near, 0.0), jnp.maximum(far, 0.0)
    # b + k a = 0 puts the pole on a root of f: a turning circle (reached) or the third root. A top
    # that starts on the pole has reached it, also below the sleeping threshold, where G0 (the
    # largest root of the resolvent) is 0 and says nothing of the third root.
    third = jnp.abs(dist0 * beta + k * g0)  # |beta (1 + k u3)|
    near, far, third = _pole_distances(
        near, far, third, dist0, x_s, x_o, g0, coeff, perp2 + beta * k * dist0, a * k, beta * k
    )
    # Next to the separatrix (a top rising towards a pole it nearly reaches: the other turning circle
    # and the third root close together by that pole) g0 - beta x_o cancels (g0 itself is the root of
    # a close pair of the resolvent, to ~sqrt(eps)); on the pole's side (the half k = -sigma) it is
    # |beta| (1 + k u_o) + |beta (1 + k u3)|, two distances solved for directly.
    g_o = g0 - beta * x_o
    g_s = g0 - beta * x_s

    def pole_side(x):
        return jnp.where(standing, x[1], x[0])

    close = g_o < 1e-3 * jnp.abs(g0)
    g_o = jnp.where(close, jnp.abs(beta) * pole_side(far) + pole_side(third), g_o)
    g_s = jnp.where(close, g_o + jnp.abs(beta) * amp, g_s)
    rate = safe_sqrt(g_s) / 2  # lambda
    m = _safe_div(jnp.abs(beta) * amp, g_s)
    p = jnp.where(g_s > 0, jnp.maximum(_safe_div(g_o, g_s), 0.0), 1.0)
    # sn0^2 = |x_s| / amp, cn0^2 = |x_o| / amp, sign(sn0 cn0) = sigma sign(du/dt). The smaller of the
    # two is formed from |x_s x_o| = (du/dt)^2 / G0 with the sign of du/dt: smooth through a start on
    # a turning circle (a top released with theta' = 0), where its square root alone is not.
    moving = amp > 0
    at_start = jnp.abs(x_s) <= jnp.abs(x_o)
    larger = jnp.where(at_start, jnp.abs(x_o), jnp.abs(x_s))
    root_large = safe_sqrt(_safe_div(larger, amp))
    root_small = sigma * _safe_div(udot, safe_sqrt(g0 * larger * amp))
    sn0 = jnp.where(moving, jnp.where(at_start, root_small, root_large), 0.0)
    cn0 = jnp.where(moving, jnp.where(at_start, root_large, root_small), 1.0)
    dn0 = jnp.where(g_s > 0, safe_sqrt(_safe_div(g0, g_s)), 1.0)
    # The time derivative of q0 (for the phase of a half that starts at its pole).
    qdot0 = _quat_times_omega(q0, omega0)
    quarter = _quarter_period(m, p)
    rho0 = _start_phase(sn0, cn0, dn0, p, quarter)
    z0 = pair(jax.lax.complex(w, z), jax.lax.complex(x, y))
    zdot0 = pair(jax.lax.complex(qdot0[..., 0], qdot0[..., 3]), jax.lax.complex(qdot0[..., 1], qdot0[..., 2]))
    closest = jnp.minimum(near, far)
    reached = (coeff == 0) & ((closest * jnp.abs(beta) < third) | (closest == 0))
    phase = _phase_parts(k * sigma > 0, near, far, third, amp, g_s, jnp.abs(beta), m, p, rho0)
    halves = dict(k=k, z0=z0, zdot0=zdot0, coeff=coeff, near=near, far=far, reached=reached, dist0=dist0,
                  phase=phase)  # fmt: skip
    halves = jax.tree.map(lambda x: jnp.broadcast_to(x, (2,) + batch), halves)
    return dict(
        a=a, w3=w3, h0=h, u0=u0, udot0=udot, amp=amp, sigma=sigma, rate=rate, m=m, p=p,
        start=(sn0, cn0, dn0), halves=halves, k1=k1, g0=g0, beta=beta, w1=w1, w2=w2,
        pole_gap=2 * jnp.minimum(up, down), rho0=rho0, quarter=quarter,
    )  # fmt: skip


def _pole_distances(near, far, third, dist0, x_s, x_o, g0, coeff, alpha_k, a_k, beta_k):
    """``near`` and ``far`` (``1 + k u`` on the start circle and on the other) and ``third``
    (``|beta (1 + k u3)|``), each solved for directly where it is far smaller than the numbers it was
    formed from.

    A top that swings close to a pole has a turning circle, or the cubic's third root, at a distance
    ``d`` from it far below ``dist0``, the offsets ``x`` and ``G0``: ``dist0 + k x`` and
    ``beta dist0 + k G0`` cancel (``d ~ 1e-20`` from ``~1e-16`` terms for a tilt of 1e-8 rad), and the
    half's phase, which steps by about ``pi`` at each pass, came out wrong by up to radians. In
    ``d = 1 + k u`` the cubic is ``F(d) = d (2 - d)(alpha_k - beta_k d) - (coeff - a_k d)^2`` with
    ``F(0) = -(b + k a)^2``, its coefficients formed without cancellation: Newton steps from the
    cancelled value find its small root (a turning circle's ``d >= 0``, the third root's ``d < 0``)
    to roundoff; next to the separatrix, where a circle and the third root are both by the pole, the
    third root's steps start from the two small roots' product over the circle's ``d``."""

    def polished(d, refine, sign):
        def newton(_, d):
            value = d * (2 - d) * (alpha_k - beta_k * d) - (coeff - a_k * d) ** 2
            slope = (2 - 2 * d) * (alpha_k - beta_k * d) - d * (2 - d) * beta_k + 2 * a_k * (coeff - a_k * d)
            step = _safe_div(value, slope)
            return jnp.where(refine & jnp.isfinite(step), sign * jnp.maximum(sign * (d - step), 0.0), d)

        return jax.lax.fori_loop(0, 3, newton, jnp.where(refine, d, 0.0))  # smaller than 3 copies

    pole_side = jnp.minimum(near, far)
    refine = pole_side < 1e-3 * jnp.maximum(dist0, jnp.maximum(jnp.abs(x_s), jnp.abs(x_o)))
    d = polished(pole_side, refine, 1.0)
    start_on_pole_side = near <= far
    near = jnp.where(refine & start_on_pole_side, d, near)
    far = jnp.where(refine & ~start_on_pole_side, d, far)
    weight = jnp.abs(beta_k)
    refine_third = (weight > 0) & (third < 1e-3 * (dist0 * weight + jnp.abs(g0)))
    # Beside a circle at d > 0 by the pole (a top next to the separatrix) the third root is the other
    # small root of F: the quadratic part gives their product, coeff^2 / (alpha_k + 2 beta_k + a_k^2).
    product = _safe_div(coeff * coeff, alpha_k + 2 * beta_k + a_k * a_k)
    beside = refine & (d > 0) & (product < 0)
    d3 = polished(jnp.where(beside, _safe_div(product, d), -_safe_div(third, weight)), refine_third, -1.0)
    third = jnp.where(refine_third, weight * jnp.abs(d3), third)
    return near, far, third


def _phase_parts(beyond, near, far, third, amp, g_s, weight, m, p, rho0):
    """Per body and half: ``int_0^t dt / (1 + k u) = slope t + wave (V(x0 + lambda t) - V(x0))``.

    ``beyond``: the pole lies beyond the start circle (``P <= P'``); otherwise the integral is taken
    half a period on (see :mod:`.heavy_phase`), with ``n' = amp |beta (1 + k u3)| / (G_s P')`` and
    ``m / n' = |beta| P' / |beta (1 + k u3)|``. Where the half does not nutate or its pole lies on a
    root (``valid`` false) the parts are those of a placeholder body.
    """
    valid = (amp > 0) & (g_s > 0) & jnp.where(beyond, near > 0, (far > 0) & (third > 0))
    near_s, far_s, third_s = (jnp.where(valid, x, 1.0) for x in (near, far, third))
    g_s = jnp.where(valid, g_s, 1.0)
    n = jnp.where(valid, jnp.where(beyond, amp / near_s, amp * third_s / (g_s * far_s)), 1.0)
    ratio = jnp.where(valid, jnp.where(beyond, weight * near_s / g_s, weight * far_s / third_s), 0.5)
    parts = _theta_parts(m, p, n, ratio)
    quarter = parts["quarter"]
    quarter = jnp.where(jnp.isfinite(quarter), quarter, 0.0)
    x0 = jnp.where(beyond, rho0, jnp.where(rho0 >= 0, rho0 - quarter, rho0 + quarter))
    slope = jnp.where(beyond, parts["slope"] / near_s, (parts["slope"] - ratio * parts["deficit"]) / far_s)
    wave = jnp.where(beyond, 1 / near_s, (1 + ratio) / far_s) * parts["c"]
    return parts, x0, slope, wave, valid


def _select_some(mask, branch, values):
    """``where(mask, branch(), values)``, with ``branch`` evaluated only for a batch that has an
    element in ``mask`` (a rare regime then costs nothing per sample in the common batch)."""

    def chosen():
        return tuple(jnp.where(mask, x, y) for x, y in zip(branch(), values, strict=True))

    return jax.lax.cond(jnp.any(mask), chosen, lambda: tuple(values))


def _root_terms(held, t, near, far):
    """:func:`.heavy_pole.pole_root_terms` at ``t``, from the body's parts and :func:`_jacobi_now`'s
    ``v = lambda t``, ``now = (sn, cn, dn)`` at ``t`` in ``held``."""
    v, now, m, p, start = (held[key] for key in ("v", "now", "m", "p", "start"))
    step = epsilon_step(now, start, held["rho0"], v, m, p, held["quarter"])
    return pole_root_terms(now, start, step, v, held["rate"], m, p, near, far)


@jax.custom_jvp
def _zero_in_value(coeff, masks, held):
    """``where(mask, coeff * term, 0)`` for the three terms of :func:`_root_terms` (at ``held``) and
    their masks, on which ``coeff`` (``b + k a``) is 0. Zero in value, so that a run without
    derivatives evaluates nothing (a branch per sample kept XLA from fusing the common batch's
    samples: 50% longer); the derivative is ``d(coeff) * term``, the terms held constant."""
    shapes = jax.eval_shape(_root_terms, *held)
    return tuple(
        jnp.zeros(jnp.broadcast_shapes(shape.shape, coeff.shape, mask.shape), shape.dtype)
        for shape, mask in zip(shapes, masks, strict=True)
    )


@_zero_in_value.defjvp
def _zero_in_value_jvp(primals, tangents):
    coeff, masks, held = primals
    zeros = _zero_in_value(coeff, masks, held)
    # Evaluated only for a batch that holds such a half.
    terms = _select_some(masks[0] | masks[1], lambda: _root_terms(*held), zeros)
    d_coeff = tangents[0]
    return zeros, tuple(jnp.where(mask, d_coeff * x, 0.0) for mask, x in zip(masks, terms, strict=True))


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
    """Both Cayley-Klein halves at time ``t`` (on the leading axis of ``half``'s arrays): their unit
    phases, signed moduli and moduli's rates, ``du/dt``, and the phases' angles."""
    k, coeff, near, far = half["k"], half["coeff"], half["near"], half["far"]
    sn, cn, dn = now
    rate, amp, sigma = body["rate"], body["amp"], body["sigma"]
    spin = k * (body["w3"] - body["a"])
    dist = near * cn * cn + far * sn * sn  # 1 + k u(t), a sum of nonnegative terms
    udot = 2 * sigma * amp * rate * sn * cn * dn
    modulus = safe_sqrt(dist / 2)
    modulus_rate = _safe_div(k * udot, 4 * modulus)
    # The phase: (1/2) [k (w3 - a) t + (b + k a) int_0^t dt / (1 + k u)].
    sn0, cn0, dn0 = body["start"]
    parts, x0, slope, wave, valid = half["phase"]
    delta_v = _theta_phase(x0 + reduced, parts) - _theta_phase(x0, parts)
    rate_safe = jnp.where(valid, rate, 1.0)
    integral = jnp.where(valid, slope * t + wave / rate_safe * delta_v, _safe_div(t, near))
    # b + k a = 0 with the pole on a root of the cubic: the terms that carry d(b + k a) (:mod:`.heavy_pole`).
    # A nutation below eps^(2/3) takes its first-order form instead (below).
    linear = (amp <= jnp.finfo(amp.dtype).eps ** (2 / 3) * body["pole_gap"]) & (body["g0"] > 0)
    on_root = (coeff == 0) & (amp > 0) & (rate > 0)
    third_mask, pole_mask = on_root & ~half["reached"] & ~linear, on_root & half["reached"]
    held = {key: body[key] for key in ("start", "rate", "m", "p", "rho0", "quarter")}
    held = jax.lax.stop_gradient((dict(held, v=reduced, now=now), t, near, far))
    third, pole_r, pole_r_dot = _zero_in_value(coeff, (third_mask, pole_mask, pole_mask), held)
    integral = jnp.where(third_mask, 0.0, integral)
    # A nutation below eps^(2/3) (steady precession, up to roundoff): its first-order form, exact in
    # value there (errors O(amp^2)) and with the derivatives of the flow, which the elliptic form's
    # square roots of the amplitude do not give. x(t) = u - u0 solves x'' = -G0 (x + k1 / 2).
    # (Also small against both poles' distances: 1 / (1 + k u) is expanded to first order.)
    k1, udot0, dist0 = body["k1"], body["udot0"], half["dist0"]

    def first_order():
        nu = safe_sqrt(jnp.where(linear, body["g0"], 1.0))
        sin_t, cos_t = _sin_cos(nu * t)
        x_lin = -(k1 / 2) * (1 - cos_t) + udot0 * sin_t / nu
        xdot_lin = -(k1 / 2) * nu * sin_t + udot0 * cos_t
        xint_lin = -(k1 / 2) * (t - sin_t / nu) + udot0 * (1 - cos_t) / nu**2
        modulus = safe_sqrt((dist0 + k * x_lin) / 2)
        integral = _safe_div(t, dist0) - k * _safe_div(xint_lin, dist0 * dist0)
        return xdot_lin, modulus, _safe_div(k * xdot_lin, 4 * modulus), integral

    udot, modulus, modulus_rate, integral = _select_some(
        linear, first_order, (udot, modulus, modulus_rate, integral)
    )
    regular_coeff = jnp.where(half["reached"], 0.0, coeff)
    phase = 0.5 * (spin * t + regular_coeff * integral + third)
    sin_phase, cos_phase = _sin_cos(phase)
    rotor = jax.lax.complex(cos_phase, sin_phase)
    regular = (_unit(half["z0"]), modulus, modulus_rate)
    # A pole on a turning circle: the modulus is sqrt(P_far / 2) J(tau) with J = sn when the start
    # circle is the pole (cn otherwise), and the phase turns uniformly.
    start_is_pole = near <= far
    scale = safe_sqrt(jnp.maximum(near, far) / 2)
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
    # A reached pole: the half is (S + i (b + k a) R) e to first order (see _pole_first_order).
    return chosen[0] * rotor, chosen[1], chosen[2], udot, phase, (pole_r, pole_r_dot)


def lagrange_top_motion(inertia, mass, com, gravity, omega0, q0, t, *, phases=False):
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
    Derivatives: every sample's Jacobian (:func:`.sample_jacobians`), so that reverse mode costs
    about what forward mode does. ``phases``: also return the size of the phases evaluated at each
    sample (:func:`.largest_phase`), shape ``batch``.
    """
    omega, q, phase = _motion(inertia, mass, com, gravity, omega0, q0, t)
    return (omega, q, phase[..., 0]) if phases else (omega, q)


def _motion_of_inputs(inertia, mass, com, gravity, omega0, q0, t):
    return lagrange_top_at(lagrange_top_parts(inertia, mass, com, gravity, omega0, q0), t)


_motion = sample_jacobians(_motion_of_inputs, (3, 0, 3, 0, 3, 4, 0))


def lagrange_top_parts(inertia, mass, com, gravity, omega0, q0) -> dict:
    """What :func:`lagrange_top_at` needs of each top, independent of time (the roots of the cubic,
    the elliptic parameter ``m``, the phases' parts): a dict of arrays of the tops' batch shape (and
    constants). Arguments as :func:`lagrange_top_motion`'s."""
    A = 0.5 * (inertia[..., 0] + inertia[..., 1])
    C = inertia[..., 2]
    return _body(A, C, mass * gravity * com[..., 2], omega0, q0)


def _jacobi_now(body, t):
    """``lambda t`` and ``(sn, cn, dn)(tau0 + lambda t)``."""
    sn0, cn0, dn0 = body["start"]
    v = body["rate"] * t
    sn_v, cn_v, dn_v, _ = _ellipj_checked(v, body["m"], body["p"])
    m = body["m"]
    # Addition theorem, written without cancellation where sn and sn0 are both near 1.
    den = cn0 * cn0 + sn0 * sn0 * dn_v * dn_v
    sn = (sn_v * cn0 * dn0 + sn0 * cn_v * dn_v) / den
    cn = (cn_v * cn0 - sn_v * sn0 * dn_v * dn0) / den
    dn = (dn_v * dn0 - m * sn_v * sn0 * cn_v * cn0) / den
    return v, (sn, cn, dn)


def lagrange_top_at(body: dict, t):
    """``(omega, q)`` of :func:`lagrange_top_motion` at times ``t`` from the tops' parts
    (:func:`lagrange_top_parts`), and the size of their phases (:func:`.largest_phase`), shape
    ``batch + (1,)``."""
    v, now = _jacobi_now(body, t)
    # The halves' leading axis in front of the samples' axes (t may have more axes than the tops).
    samples = max(jnp.ndim(t), body["halves"]["k"].ndim - 1)
    halves = jax.tree.map(
        lambda x: x.reshape((2,) + (1,) * (samples - x.ndim + 1) + x.shape[1:]), body["halves"]
    )
    ph, mod, mod_rate, udot, angle, first = _half(halves, body, t, now, v)
    # Held in memory: read by every component of omega and q (each would recompute them otherwise).
    ph_re, ph_im, mod, mod_rate, udot = _materialised((jnp.real(ph), jnp.imag(ph), mod, mod_rate, udot))
    (ph_p, ph_m), (mod_p, mod_m), (rate_p, rate_m) = jax.lax.complex(ph_re, ph_im), mod, mod_rate
    q = [mod_p * jnp.real(ph_p), mod_m * jnp.real(ph_m), mod_m * jnp.imag(ph_m), mod_p * jnp.imag(ph_p)]
    # omega_1 + i omega_2 = (i/2)(h + i du/dt) / (A_- A_+) * E_- conj(E_+); at a reached pole the
    # ratio (h + i du/dt) / A_pole is taken from its limit form.
    a = body["a"]
    up_pole, down_pole = halves["reached"]
    # h = b - a u from the pole the top is nearer: (b - a) + a (1 - u) or (b + a) - a (1 + u).
    dist_m, dist_p = 2 * mod_m * mod_m, 2 * mod_p * mod_p
    h = jnp.where(dist_m <= dist_p, halves["coeff"][1] + a * dist_m, halves["coeff"][0] - a * dist_p)
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
    sleep_up, sleep_down = down_pole & tiny, up_pole & tiny & ~down_pole
    z_up, z_down = halves["z0"]
    tilt_args = (a, body["beta"], z_up, z_down, body["w1"], body["w2"], t, ph_p, ph_m)

    def at_poles(q, transverse):
        top = (halves["k"], halves["coeff"], halves["reached"], body["w3"] - a)
        q, transverse = _pole_first_order(q, transverse, (ph_p, ph_m), mod, mod_rate, first, top)
        zeta, big_w, tilt_rate_up, tilt_rate_down = _sleeping(*tilt_args)
        # The other half's modulus is constant to first order (its elliptic form's derivatives are
        # those of roots a roundoff apart, times roundoff: O(1) noise for a top 1e-16 off the pole).
        held_p, held_m = jax.lax.stop_gradient(mod_p), jax.lax.stop_gradient(mod_m)
        q[0] = jnp.where(sleep_up, held_p * jnp.real(ph_p), q[0])
        q[3] = jnp.where(sleep_up, held_p * jnp.imag(ph_p), q[3])
        q[1] = jnp.where(sleep_down, held_m * jnp.real(ph_m), q[1])
        q[2] = jnp.where(sleep_down, held_m * jnp.imag(ph_m), q[2])
        q[1] = jnp.where(sleep_up, jnp.real(zeta), q[1])
        q[2] = jnp.where(sleep_up, jnp.imag(zeta), q[2])
        q[0] = jnp.where(sleep_down, jnp.real(big_w), q[0])
        q[3] = jnp.where(sleep_down, jnp.imag(big_w), q[3])
        transverse = jnp.where(sleep_up, tilt_rate_up, transverse)
        transverse = jnp.where(sleep_down, tilt_rate_down, transverse)
        return q, transverse

    # Evaluated only where a batch holds a top at a reached pole (the common batch holds none). This
    # also makes XLA materialise the components before they are stacked.
    q, transverse = jax.lax.cond(
        jnp.any(up_pole | down_pole), at_poles, lambda q, transverse: (list(q), transverse), q, transverse
    )
    w3 = jnp.broadcast_to(body["w3"], transverse.shape)
    omega = jnp.stack([jnp.real(transverse), jnp.imag(transverse), w3], axis=-1)
    # A sleeping top's modes turn at a t / 2 and |w| t, |w| <= sqrt(a^2 / 4 + |beta| / 2).
    modes = jnp.where(
        sleep_up | sleep_down, (jnp.abs(a) / 2 + safe_sqrt(a * a / 4 + jnp.abs(body["beta"]) / 2)) * t, 0.0
    )
    phase = largest_phase(v, angle[0], angle[1], modes)
    return omega, jnp.stack(q, axis=-1), jnp.broadcast_to(phase, transverse.shape)[..., None]


def _pole_first_order(q, transverse, phases, mod, mod_rate, first, top):
    """A batch with a half at a reached pole: its first-order term in ``b + k a`` (zero in value) added
    to ``q``, and the derivative of ``omega_1 + i omega_2`` taken as that of ``2 (conj(Z_+) Z_-' -
    conj(Z_+') Z_-)`` (``Z_+ = w + iz``, ``Z_- = x + iy``), which holds on any motion and needs no division
    by a half's modulus, in place of that of the pole's limit form (which has none of ``b + k a``)."""
    k, coeff, reached, spin = top
    # (b + k a) R and its rate, zero in value; the phases' rates (k spin + (b + k a) / (1 + k u)) / 2.
    shift, shift_rate = first
    phase_rate = 0.5 * (k * spin + _safe_div(jnp.where(reached, 0.0, coeff), 2 * mod * mod))
    halves, rates = [], []
    for i in range(2):
        z = jax.lax.complex(mod[i], shift[i]) * phases[i]
        halves.append(z)
        rates.append(
            jax.lax.complex(mod_rate[i], shift_rate[i]) * phases[i] + _times_i(_times(phase_rate[i], z))
        )
    q = [
        q[0] - shift[0] * jnp.imag(phases[0]),
        q[1] - shift[1] * jnp.imag(phases[1]),
        q[2] + shift[1] * jnp.real(phases[1]),
        q[3] + shift[0] * jnp.real(phases[0]),
    ]
    bilinear = 2 * (jnp.conj(halves[0]) * rates[1] - jnp.conj(rates[0]) * halves[1])
    use = (reached[0] | reached[1]) & jnp.isfinite(jnp.real(bilinear)) & jnp.isfinite(jnp.imag(bilinear))
    bilinear = jnp.where(use, bilinear, 0.0)
    held = jax.lax.stop_gradient(transverse) + (bilinear - jax.lax.stop_gradient(bilinear))
    return q, jnp.where(use, held, transverse)


def _sleeping(a, beta, z_up, z_down, w1, w2, t, ph_p, ph_m):
    """A top sleeping at a pole up to a wobble below eps^(2/3): the linearised motion, zero in value
    at the equilibrium and carrying the derivatives that start a wobble (the pole form's direction
    of the wobble is undefined there). The tilt T = X + iY of the symmetry axis (T = -2i (x+iy)(w+iz))
    is a sum of circular modes exp(i lambda t), lambda^2 - s a lambda + s beta / 2 = 0, s = +1 upright
    (T' = -i W^2 Omega), s = -1 hanging straight down (T' = i Z^2 conj(Omega)).

    Returns the half ``x + iy`` of a top upright, ``w + iz`` of one hanging, and the transverse
    ``omega_1 + i omega_2`` of either."""
    tilt0 = -2 * _times_i(z_down * z_up)
    omega0_t = jax.lax.complex(w1, w2)
    rate_up, rate_down = -_times_i(z_up**2 * omega0_t), _times_i(z_down**2 * jnp.conj(omega0_t))
    turn = _sin_cos(a * t / 2)[::-1]
    # Both poles' modes in one evaluation on a leading axis of 2 (half the program of two calls).
    shape = jnp.broadcast_shapes(*(jnp.shape(x) for x in (a, beta, tilt0, rate_up, rate_down, t)))
    s = jnp.asarray([1.0, -1.0], a.dtype).reshape((2,) + (1,) * len(shape))
    rate0 = jnp.stack([jnp.broadcast_to(rate_up, shape), jnp.broadcast_to(rate_down, shape)])
    tilt, tilt_rate = _tilt_modes(s, a, beta, tilt0, rate0, t, turn)
    zeta, big_w = _times_i(tilt[0] * jnp.conj(ph_p)) / 2, _times_i(tilt[1] * jnp.conj(ph_m)) / 2
    return (
        zeta,
        big_w,
        _times_i(tilt_rate[0] * jnp.conj(ph_p) ** 2),
        _times_i(jnp.conj(tilt_rate[1]) * ph_m**2),
    )


def _times_i(z):
    return jax.lax.complex(-jnp.imag(z), jnp.real(z))


def _tilt_modes(s, a, beta, tilt0, rate0, t, turn):
    """``T(t)`` and ``T'(t)`` for ``T = c1 exp(i l1 t) + c2 exp(i l2 t)`` with ``T(0)``, ``T'(0)`` given and
    ``l`` the roots of ``l^2 - s a l + s beta / 2 = 0`` (complex below the sleeping threshold).

    With ``l = sigma +- w`` (``sigma = s a / 2``, ``w^2 = a^2 / 4 - s beta / 2``), in real functions:
    ``T = e^(i sigma t) (T(0) C + (T'(0) - i sigma T(0)) S)`` with ``C = cos(w t)`` and ``S = sin(w t) / w``
    (``cosh``, ``sinh`` of ``|w| t`` below the threshold, ``S = t`` at it) and
    ``T' = i sigma T + e^(i sigma t) (-w^2 T(0) S + (T'(0) - i sigma T(0)) C)``. ``turn`` is
    ``(cos, sin)`` of ``a t / 2``: ``e^(i sigma t)`` for ``s = 1``, its conjugate for ``s = -1``.
    """
    sigma = s * a / 2
    w2 = a * a / 4 - s * beta / 2
    w = safe_sqrt(jnp.abs(w2))
    w_safe = jnp.where(w > 0, w, 1.0)
    sin_wt, cos_wt = _sin_cos(w * t)
    grow = jnp.expm1(jnp.where(w2 < 0, w * t, 0.0))
    cosh_wt = 1 + grow * grow / (2 * (1 + grow))  # (e + 1/e) / 2 with e = 1 + grow
    sinh_wt = grow * (2 + grow) / (2 * (1 + grow))  # (e - 1/e) / 2
    c = jnp.where(w2 < 0, cosh_wt, cos_wt)
    sw = jnp.where(w > 0, jnp.where(w2 < 0, sinh_wt, sin_wt) / w_safe, t)
    drift = rate0 - _times_i(_times(sigma, tilt0))  # T'(0) - i sigma T(0)
    cos_h, sin_h = turn
    rotor = jax.lax.complex(*jnp.broadcast_arrays(cos_h, s * sin_h))
    tilt = rotor * (_times(c, tilt0) + _times(sw, drift))
    tilt_rate = _times_i(_times(sigma, tilt)) + rotor * (_times(-w2 * sw, tilt0) + _times(c, drift))
    return tilt, tilt_rate
