"""The torque-free rigid body in closed form: omega(t) by Jacobi elliptic functions.

Landau & Lifshitz, Mechanics, section 37. With the principal moments sorted I1 <= I2 <= I3 and the
conserved ``L^2`` and ``2E``, the body-frame angular velocity circles axis ``c`` (the largest moment
when ``L^2 > 2 E I2``, the smallest otherwise) and, with ``(a, b, c)`` = ``(1, 2, 3)`` or ``(3, 2, 1)``::

    omega_a = A_a cn(tau | m),  omega_b = A_b sn(tau | m),  omega_c = ±A_c dn(tau | m),
    tau = lambda t + tau0.

The initial phase ``tau0`` enters through the addition theorems with sn, cn, dn of ``tau0`` read off
``omega0`` directly, so no incomplete elliptic integral is needed. Every difference of conserved
quantities is written as ``L^2 - 2 E I_j = sum_i I_i (I_i - I_j) omega_i^2``, which has no cancellation, and
``1 - m`` is computed on its own, so the motion is accurate up to the separatrix (m -> 1) and for
nearly symmetric bodies (m -> 0). Steady rotations (spin about a principal axis, a sphere) return
``omega0`` unchanged, with the derivatives of the linearised flow ``exp(J t)`` (finite and exact: see
``_steady_omega``).
"""

import equinox as eqx
import jax
import jax.numpy as jnp

from .._checks import (
    call_checked,
    check_batch_shapes,
    check_finite,
    check_last_axis,
    check_rotation_quaternion,
    collected_failures,
    common_float,
)
from .._dynamics.inertia import check_inertia
from .._kinematics.quaternion import _quat_multiply
from .._numerics import safe_norm
from .._types import Quaternion, QuaternionOut, Scalar, ScalarOut, Vector, VectorOut
from .carlson import _carlson_rf_rj
from .elliptic import _ellipj_checked, ellipkm1


def _sorted_frame(inertia, omega0):
    """Moments ascending, omega permuted alike, and the permutation's parity (+1 even, -1 odd).

    Every gather here and below indexes with a permutation of ``0, 1, 2``, so it is declared in
    bounds: the default out-of-bounds handling adds masking to each gather and to its derivatives,
    a sizeable part of every compiled copy of the model.
    """
    perm = jnp.argsort(inertia, axis=-1)
    moments = jnp.take_along_axis(inertia, perm, axis=-1, mode="promise_in_bounds")
    omega = jnp.take_along_axis(omega0, perm, axis=-1, mode="promise_in_bounds")
    p0, p1, p2 = perm[..., 0], perm[..., 1], perm[..., 2]
    inversions = sum((x > y).astype(jnp.int32) for x, y in ((p0, p1), (p0, p2), (p1, p2)))
    parity = jnp.where(inversions % 2 == 0, 1.0, -1.0).astype(inertia.dtype)
    return perm, moments, omega, parity


def _take(x, index):
    """``take_along_axis`` on the last axis, ``index`` broadcast against ``x``'s batch axes."""
    shape = jnp.broadcast_shapes(x.shape[:-1], index.shape[:-1]) + index.shape[-1:]
    return jnp.take_along_axis(
        jnp.broadcast_to(x, shape[:-1] + x.shape[-1:]),
        jnp.broadcast_to(index, shape),
        axis=-1,
        mode="promise_in_bounds",
    )


def _momentum_defect(moments, x, j):
    """``L^2 - 2 E I_j`` written without cancellation: ``sum_i I_i (I_i - I_j) omega_i^2``."""
    return sum(moments[..., i] * (moments[..., i] - moments[..., j]) * x[..., i] for i in range(3) if i != j)


def _safe_div(num, den):
    ok = den != 0
    return jnp.where(ok, num / jnp.where(ok, den, 1.0), 0.0)


def _clip(x, low, high):
    """``clip`` for roundoff only: the value is clipped, the derivative is that of ``x``.

    At a symmetric body ``m`` and ``n`` touch 0 from above under either labelling of the equal axes;
    the formulas continue analytically to ``m < 0``, so the derivative of the unclipped expression is
    the derivative of the motion (``jnp.clip`` would halve it at the boundary).
    """
    return x + jax.lax.stop_gradient(jnp.clip(x, low, high) - x)


def _solution_parameters(moments, omega):
    """Amplitudes, rate, parameter m and 1 - m of the elliptic solution, in the sorted frame."""
    x = omega * omega
    D = [_momentum_defect(moments, x, j) for j in range(3)]
    around_largest = D[1] >= 0  # L^2 >= 2 E I2: omega circles the axis of the largest moment
    I1, I2, I3 = moments[..., 0], moments[..., 1], moments[..., 2]
    Ia = jnp.where(around_largest, I1, I3)
    Ic = jnp.where(around_largest, I3, I1)
    Ib = I2
    Da = jnp.where(around_largest, D[0], D[2])
    Dc = jnp.where(around_largest, D[2], D[0])
    Db = D[1]
    amp_a = jnp.sqrt(jnp.maximum(_safe_div(-Dc, Ia * (Ic - Ia)), 0.0))
    amp_b = jnp.sqrt(jnp.maximum(_safe_div(-Dc, Ib * (Ic - Ib)), 0.0))
    amp_c = jnp.sqrt(jnp.maximum(_safe_div(Da, Ic * (Ic - Ia)), 0.0))
    rate = jnp.sqrt(jnp.maximum(_safe_div((Ic - Ib) * Da, Ia * Ib * Ic), 0.0))
    m = _clip(_safe_div((Ib - Ia) * -Dc, (Ic - Ib) * Da), 0.0, 1.0)
    p = _clip(_safe_div((Ic - Ia) * Db, (Ic - Ib) * Da), 0.0, 1.0)
    return around_largest, (amp_a, amp_b, amp_c), rate, m, p


def _checked(inertia, omega0, t, where):
    """Run-time value checks of the public closed forms (``eqx.error_if``: also under jit/vmap)."""
    inertia = check_inertia(inertia, name=f"{where}: inertia")
    omega0 = check_finite(omega0, "omega0", where)
    t = t if t is None else check_finite(t, "t", where)
    return inertia, omega0, t


def _body_arrays(t, *arrays):
    """The body's arrays broadcast against each other (last axis kept) and the batch shape with ``t``.

    ``t`` stays apart: what depends on the body only (its elliptic parameters, K, G(K), the initial
    phase) keeps the body's shape and is computed once per body, not per sample time.
    """
    body = jnp.broadcast_shapes(*(a.shape[:-1] for a in arrays))
    return [jnp.broadcast_to(a, body + a.shape[-1:]) for a in arrays], jnp.broadcast_shapes(body, t.shape)


def _broadcast_inputs(inertia, omega0, t, checked=True):
    inertia, omega0, t = common_float(inertia, omega0, t, names=["inertia", "omega0", "t"])
    check_last_axis(inertia, 3, "inertia")
    check_last_axis(omega0, 3, "omega0")
    check_batch_shapes("torque_free_omega", ("inertia", inertia, 1), ("omega0", omega0, 1), ("t", t, 0))
    if checked:
        inertia, omega0, t = _checked(inertia, omega0, t, "torque_free_omega")
    (inertia, omega0), batch = _body_arrays(t, inertia, omega0)
    return inertia, omega0, t, batch


def _motion_parts(inertia, omega0, t):
    """The elliptic solution at ``t`` and the pieces the orientation reuses (all in the sorted frame)."""
    perm, moments, omega, parity = _sorted_frame(inertia, omega0)
    around_largest, (amp_a, amp_b, amp_c), rate, m, p = _solution_parameters(moments, omega)
    w_a = jnp.where(around_largest, omega[..., 0], omega[..., 2])
    w_b = omega[..., 1]
    w_c = jnp.where(around_largest, omega[..., 2], omega[..., 0])
    sign_c = jnp.where(w_c < 0, -1.0, 1.0).astype(omega.dtype)
    # Jacobi functions of the initial phase, straight from omega0.
    # amp_a and amp_b vanish together (pure spin about axis c): phase 0, so that cn0^2 + sn0^2 = 1.
    cn0 = jnp.where(amp_a > 0, w_a / jnp.where(amp_a > 0, amp_a, 1.0), 1.0)
    sn0 = _safe_div(w_b, amp_b)
    dn0 = jnp.where(amp_c > 0, jnp.abs(w_c) / jnp.where(amp_c > 0, amp_c, 1.0), 1.0)
    # The sign of d(tau)/dt follows the sense of rotation about axis c; an odd relabelling of the
    # body axes reverses it (it flips the cross product in Euler's equations).
    u = parity * sign_c * rate * t
    sn, cn, dn, _ = _ellipj_checked(u, 1 - p, p)  # the AGM of p stays per body
    # = 1 - m sn^2 sn0^2, written without its cancellation when sn and sn0 are both near 1 (the
    # separatrix, where m = 1).
    denominator = cn0 * cn0 + sn0 * sn0 * dn * dn
    sn_t = (sn * cn0 * dn0 + sn0 * cn * dn) / denominator
    cn_t = (cn * cn0 - sn * sn0 * dn * dn0) / denominator
    dn_t = (dn * dn0 - m * sn * sn0 * cn * cn0) / denominator
    out_a, out_b, out_c = amp_a * cn_t, amp_b * sn_t, sign_c * amp_c * dn_t
    sorted_out = jnp.stack(
        [jnp.where(around_largest, out_a, out_c), out_b, jnp.where(around_largest, out_c, out_a)], axis=-1
    )
    # rate = 0: spin about a principal axis of a symmetric body or a sphere. w_a = w_c = 0: spin about
    # the intermediate axis, the unstable equilibrium on the separatrix.
    steady = (rate == 0) | ((w_a == 0) & (w_c == 0))
    sorted_out = jnp.where(steady[..., None], omega, sorted_out)
    omega_t = _take(sorted_out, jnp.argsort(perm, axis=-1))
    return omega_t, dict(
        perm=perm,
        moments=moments,
        omega=omega,
        around_largest=around_largest,
        rate=rate,
        m=m,
        p=p,
        steady=steady,
        u=u,
        speed=parity * sign_c * rate,
        start=(sn0, cn0, dn0),
        now=(sn_t, cn_t, dn_t),
    )


def torque_free_omega(inertia: Vector, omega0: Vector, t: Scalar) -> VectorOut:
    """Body-frame angular velocity of a torque-free body at time ``t``, in closed form.

    The solution in Jacobi elliptic functions (Landau & Lifshitz, section 37), on both sides of the
    separatrix.
    Exact up to roundoff: no integration, so the cost does not grow with ``t``.

    Derivatives (forward and reverse) are those of the flow and finite everywhere, steady rotations
    included (spin about any principal axis, a sphere: there ``d omega(t) / d omega0 = exp(J t)`` grows
    like ``cosh(lambda t)`` about the intermediate axis). The derivative with respect to ``inertia``
    loses about ``eps / gap`` relative accuracy as the moments meet (``gap`` the relative difference of
    two moments; measured 6e-3 at ``gap = 1e-15``, 1e-8 at 1e-9, 7e-12 at 1e-6,
    ``tests/test_extreme_bodies.py``): the parametrisation's ``1 / (I_j - I_k)`` terms cancel. Exactly
    equal moments are exact; for gaps below ~1e-9 differentiate ``simulate`` instead.

    **Arguments:**

    - `inertia`: principal moments ``(..., 3)`` in any order (kg m^2). Non-physical moments (beyond
      the flat plate, non-positive) are an error at run time.
    - `omega0`: angular velocity at ``t = 0`` in body-frame components (rad/s), ``(..., 3)``.
    - `t`: time (s), broadcast against the batch axes of `inertia` and `omega0`: for a batch of
      bodies at T times use ``inertia[:, None]``, ``omega0[:, None]``, ``ts[None, :]``.

    **Returns:** ``omega(t)`` in body-frame components (rad/s), shape ``batch + (3,)`` with ``batch``
    the broadcast of the bodies' batch axes with ``t``'s shape. NaN or inf in any input raises at run
    time.
    """
    return call_checked(_omega_program, _omega_failures, inertia, omega0, t)


# One compiled program per shape (eager calls would dispatch op by op). Inputs with values are checked
# by a program of their own that returns the failed conditions (a ValueError is raised from them), so
# neither program holds a host callback and JAX's persistent cache keeps both: a new process compiles
# nothing. Inputs without values (the user's jit or vmap) get eqx.error_if checks in the program.
@eqx.filter_jit
def _omega_program(inertia, omega0, t, *, checked):
    return _torque_free_omega(inertia, omega0, t, checked=checked)


@eqx.filter_jit
def _omega_failures(inertia, omega0, t):
    with collected_failures() as failures:
        _broadcast_inputs(inertia, omega0, t)
    return list(failures)


def _torque_free_omega(inertia, omega0, t, *, checked):
    """:func:`torque_free_omega`; ``checked=False`` leaves out its run-time value checks (equinox
    errors, host callbacks: JAX's persistent cache keeps no program that holds one) for callers
    whose values are valid by construction, such as the fit's parametrised moments."""
    inertia, omega0, t, batch = _broadcast_inputs(inertia, omega0, t, checked)
    steady = _steady(inertia, omega0)
    # A generic body stands in for steady ones (the elliptic parametrisation is singular there: its
    # amplitudes are square roots of zero), whose motion and derivatives are _steady_omega's.
    inertia_g = jnp.where(steady[..., None], jnp.array([1.0, 2.0, 3.0], inertia.dtype), inertia)
    omega0_g = jnp.where(steady[..., None], jnp.array([1.0, 1.0, 1.0], inertia.dtype), omega0)
    omega_g = _motion_parts(inertia_g, omega0_g, t)[0]
    omega = jnp.where(steady[..., None], _steady_omega(inertia, omega0, t, steady), omega_g)
    return jnp.broadcast_to(omega, batch + (3,))


def torque_free_period(inertia: Vector, omega0: Vector) -> ScalarOut:
    """Period ``4 K(m) / lambda`` of the body-frame angular velocity of a torque-free body.

    Half of it is the time between two tennis-racket flips (``omega_b`` changes sign every
    ``2K/lambda``).

    **Arguments:**

    - `inertia`: principal moments ``(..., 3)`` in any order (kg m^2). Non-physical moments are an
      error at run time.
    - `omega0`: angular velocity in body-frame components (rad/s), ``(..., 3)``, broadcast against
      `inertia`.

    **Returns:** the period (s), shape ``(...)``: infinite on the separatrix and for steady rotation
    (``lambda = 0``). NaN or inf in any input raises at run time.
    """
    return call_checked(_period_program, _period_failures, inertia, omega0)


def _period_inputs(inertia, omega0, checked):
    inertia, omega0 = common_float(inertia, omega0, names=["inertia", "omega0"])
    check_last_axis(inertia, 3, "inertia")
    check_last_axis(omega0, 3, "omega0")
    check_batch_shapes("torque_free_period", ("inertia", inertia, 1), ("omega0", omega0, 1))
    if checked:
        inertia, omega0, _ = _checked(inertia, omega0, None, "torque_free_period")
    return jnp.broadcast_arrays(inertia, omega0)


@eqx.filter_jit
def _period_failures(inertia, omega0):
    with collected_failures() as failures:
        _period_inputs(inertia, omega0, checked=True)
    return list(failures)


@eqx.filter_jit
def _period_program(inertia, omega0, *, checked):
    inertia, omega0 = _period_inputs(inertia, omega0, checked)
    _, moments, omega, _ = _sorted_frame(inertia, omega0)
    rate = _solution_parameters(moments, omega)[2]
    # rate = 0 (a sphere, a symmetric body in steady rotation): the period is infinite; a generic
    # body stands in so that the square roots of zero do not make the gradient NaN.
    still = rate == 0
    moments = jnp.where(still[..., None], jnp.array([1.0, 2.0, 3.0], moments.dtype), moments)
    omega = jnp.where(still[..., None], jnp.array([1.0, 1.0, 1.0], moments.dtype), omega)
    _, _, rate, _, p = _solution_parameters(moments, omega)
    quarter = ellipkm1(jnp.where(p > 0, p, 1.0))
    return jnp.where(~still & (p > 0), 4.0 * quarter / rate, jnp.inf)


# --------------------------------------------------------------------------------------------------
# Orientation


def _reduced_phase(sn, cn, dn, p, n, quarter=None):
    """Reduced phase of the point ``(sn, cn, dn)`` of the elliptic solution and ``G`` there.

    ``G(tau) = int_0^tau dtau' / (1 + n sn^2(tau')) = Pi(-n; am(tau) | m)``. The point fixes ``tau`` up to
    multiples of ``2K``: ``tau = rho + 2 j K`` with ``|rho| <= K``, and then ``G(tau) = gamma + 2 j G(K)``.
    Returns ``rho``, ``gamma``, ``am(rho)`` and ``quarter = (K, G(K))`` (DLMF 19.25.1-2; pass them back
    for further points of the same body, or None to evaluate them in the same ``R_F``/``R_J`` call:
    one duplication loop fewer to compile and differentiate). Carlson forms (DLMF 19.25.5, 19.25.14)
    on ``|sn| <= 1/sqrt 2``; above, the same integrals measured back from ``K`` (substituting
    ``theta -> pi/2 - theta``), whose ``R_F``/``R_J`` arguments are ``O(p)`` but never zero, so that the
    terms are positive and ``rho``, ``gamma`` keep their accuracy as ``p = 1 - m -> 0``. One
    ``R_F``/``R_J`` evaluation per point: the two forms' arguments are selected before it (both are
    positive, so gradients stay finite). ``p = 0`` is handled by the caller.
    """
    c = jnp.abs(cn)
    s = jnp.abs(sn)
    sign_s = jnp.where(sn < 0, -1.0, 1.0).astype(sn.dtype)
    sign_c = jnp.where(cn < 0, -1.0, 1.0).astype(sn.dtype)
    direct = s * s <= 0.5
    pc = jnp.where(p > 0, p, jnp.ones_like(p))
    pole = 1 + n * s * s
    args = (
        jnp.where(direct, c * c, pc * s * s),
        dn * dn,
        jnp.where(direct, jnp.ones_like(s), pc),
        jnp.where(direct, pole, pc * pole / (1 + n)),
    )
    weight = n / (1 + n) * pc / 3
    if quarter is None:  # K = R_F(0, 1, p), G(K) from R_J(0, 1, p, p / (1 + n)), stacked with the point
        extra = (jnp.zeros_like(pc), jnp.ones_like(pc), pc, pc / (1 + n))
        rf, rj = _carlson_rf_rj(
            *(jnp.stack(jnp.broadcast_arrays(a, b)) for a, b in zip(args, extra, strict=True))
        )
        quarter = rf[1], (rf[1] + weight * rj[1]) / (1 + n)
        rf, rj = rf[0], rj[0]
    else:
        rf, rj = _carlson_rf_rj(*args)
    quarter_f, quarter_g = quarter
    f = sign_s * jnp.where(direct, s * rf, quarter_f - c * rf)
    g = sign_s * jnp.where(
        direct, s * rf - (n / 3) * s**3 * rj, quarter_g - (c * rf + weight * c**3 * rj) / (1 + n)
    )
    return sign_c * f, sign_c * g, jnp.arctan2(sign_c * sn, c), quarter


def _half_angles(momentum):
    """Half-angle cosines and sines of the 3-1-3 angles ``theta`` (nutation, in [0, pi]) and ``psi``
    (spin, in (-pi, pi]) with ``momentum / |momentum| = (sin theta sin psi, sin theta cos psi, cos theta)``.

    Formed from the components without dividing by ``sin theta`` and without cancellation.
    """
    lx, ly, lc = momentum[..., 0], momentum[..., 1], momentum[..., 2]
    size = safe_norm(momentum)
    st = safe_norm(momentum[..., :2])
    up = lc >= 0
    t_cos = jnp.where(up, size + lc, st)
    t_sin = jnp.where(up, st, size - lc)
    t_norm = safe_norm(jnp.stack([t_cos, t_sin], axis=-1))
    t_norm = jnp.where(t_norm > 0, t_norm, 1.0)
    right = ly >= 0
    sign_x = jnp.where(lx < 0, -1.0, 1.0).astype(momentum.dtype)
    p_cos = jnp.where(right, st + ly, jnp.abs(lx))
    p_sin = jnp.where(right, lx, sign_x * (st - ly))
    p_norm = safe_norm(jnp.stack([p_cos, p_sin], axis=-1))
    p_cos = jnp.where(p_norm > 0, p_cos, 1.0)
    p_norm = jnp.where(p_norm > 0, p_norm, 1.0)
    return t_cos / t_norm, t_sin / t_norm, p_cos / p_norm, p_sin / p_norm


def _nutation_spin_quat(momentum):
    """``Rx(theta) Rz(psi)`` as a quaternion (it turns ``momentum`` onto ``+z``) and ``psi`` in (-pi, pi]."""
    ct, st, cp, sp = _half_angles(momentum)
    q = jnp.stack([ct * cp, st * cp, -st * sp, ct * sp], axis=-1)
    return q, 2 * jnp.arctan2(sp, cp)


def _steady(inertia, omega0):
    """Rotations about a fixed body axis: a principal axis, or any axis of a sphere, or one in the
    degenerate plane of a symmetric body (also ``omega0 = 0``)."""
    _, moments, omega, _ = _sorted_frame(inertia, omega0)
    _, _, rate, _, _ = _solution_parameters(moments, omega)
    zeros = sum((omega[..., i] == 0).astype(jnp.int32) for i in range(3))
    return (rate == 0) | (zeros >= 2)


def _series_or(y, terms, closed):
    """``sum_n y^n / (2n + k)!`` (the first coefficients given in ``terms``) for small ``|y|``, else
    ``closed(y)`` evaluated at a harmless point where unused."""
    small = jnp.abs(y) < 1e-2
    series = jnp.zeros_like(y)
    for coefficient in reversed(terms):
        series = series * y + coefficient
    return jnp.where(small, series, closed(jnp.where(small, jnp.ones_like(y), y)))


def _steady_omega(inertia, omega0, t, steady):
    """``omega0`` (the motion of a steady rotation) carrying the derivatives of the flow there.

    Along the constant solution the variational equations have constant coefficients:
    ``d omega(t) / d omega0 = exp(J t)`` and ``d omega(t) / d inertia = int_0^t exp(J s) ds B`` with
    ``J = df/d omega``, ``B = df/d inertia`` of Euler's equations at ``omega0`` (any labelling of the
    axes: the cyclic form is symmetric). Every steady rotation (a principal axis, a sphere, a symmetric
    body about an axis of its degenerate plane) has ``J^3 = c J`` with ``c = tr(J^2) / 2``
    (``lambda^2`` of :func:`rigidjax.spin_stability`), so ``exp(J t) = 1 + g1 J + g2 J^2`` with
    ``g1 = sinh(x) / sqrt(c)``, ``g2 = (cosh(x) - 1) / c``, ``x = sqrt(c) t`` (circular for ``c < 0``),
    which is exact: growth about the intermediate axis, oscillation about the others, linear drift
    in a degenerate plane. The value is ``omega0`` exactly; unused entries get harmless inputs. The
    flow matrices are only formed for derivatives (a custom JVP): the value costs nothing.
    """
    safe_w = jnp.where(steady[..., None], omega0, jnp.zeros_like(omega0))
    safe_i = jnp.where(steady[..., None], inertia, jnp.ones_like(inertia))
    return _linearised_flow(
        safe_i, safe_w, jnp.broadcast_to(t, jnp.broadcast_shapes(omega0.shape[:-1], jnp.shape(t)))
    )


@jax.custom_jvp
def _linearised_flow(inertia, omega, t):
    """``omega`` at every time ``t`` (a steady rotation), whose tangent is the linearised flow."""
    return jnp.broadcast_to(omega, t.shape + (3,))


@_linearised_flow.defjvp
def _linearised_flow_jvp(primals, tangents):
    # The tangent of t does not enter: a steady rotation does not change with time. The primals are
    # constants of the tangent map (second derivatives along the steady rotation are not provided).
    d_inertia, d_omega, _ = tangents
    flow, drive = _flow_matrices(*(jax.lax.stop_gradient(x) for x in primals))
    tangent = (flow @ d_omega[..., None])[..., 0] + (drive @ d_inertia[..., None])[..., 0]
    return _linearised_flow(*primals), tangent


def _flow_matrices(i_sg, w_sg, t_sg):
    """``exp(J t)`` and ``int_0^t exp(J s) ds B`` of :func:`_steady_omega`."""
    dtype = w_sg.dtype
    I1, I2, I3 = i_sg[..., 0], i_sg[..., 1], i_sg[..., 2]
    w1, w2, w3 = w_sg[..., 0], w_sg[..., 1], w_sg[..., 2]
    k1, k2, k3 = (I2 - I3) / I1, (I3 - I1) / I2, (I1 - I2) / I3
    zero = jnp.zeros_like(w1)
    J = jnp.stack(
        [
            jnp.stack([zero, k1 * w3, k1 * w2], -1),
            jnp.stack([k2 * w3, zero, k2 * w1], -1),
            jnp.stack([k3 * w2, k3 * w1, zero], -1),
        ],
        -2,
    )
    a, b, c = w2 * w3, w3 * w1, w1 * w2
    B = jnp.stack(
        [
            jnp.stack([-k1 * a / I1, a / I1, -a / I1], -1),
            jnp.stack([-b / I2, -k2 * b / I2, b / I2], -1),
            jnp.stack([c / I3, -c / I3, -k3 * c / I3], -1),
        ],
        -2,
    )
    J2 = J @ J
    y = 0.5 * jnp.trace(J2, axis1=-2, axis2=-1) * t_sg * t_sg  # c t^2 = x^2 (negative: circular)

    def sh(y):  # sinh(x) / x
        r = jnp.sqrt(jnp.abs(y))
        return jnp.where(y > 0, jnp.sinh(r), jnp.sin(r)) / r

    def ch(y):  # (cosh(x) - 1) / x^2 = 2 sinh(x / 2)^2 / x^2
        r = jnp.sqrt(jnp.abs(y))
        return 2 * jnp.where(y > 0, jnp.sinh(r / 2), jnp.sin(r / 2)) ** 2 / jnp.abs(y)

    def sx(y):  # (sinh(x) - x) / x^3
        r = jnp.sqrt(jnp.abs(y))
        return jnp.where(y > 0, (jnp.sinh(r) - r) / (y * r), (r - jnp.sin(r)) / (-y * r))

    g1 = t_sg * _series_or(y, [1.0, 1 / 6, 1 / 120, 1 / 5040, 1 / 362880], sh)
    g2 = t_sg**2 * _series_or(y, [1 / 2, 1 / 24, 1 / 720, 1 / 40320, 1 / 3628800], ch)
    g3 = t_sg**3 * _series_or(y, [1 / 6, 1 / 120, 1 / 5040, 1 / 362880, 1 / 39916800], sx)
    eye = jnp.eye(3, dtype=dtype)
    flow = eye + g1[..., None, None] * J + g2[..., None, None] * J2
    drive = (t_sg[..., None, None] * eye + g2[..., None, None] * J + g3[..., None, None] * J2) @ B
    return flow, drive


def _broadcast_motion_inputs(inertia, omega0, q0, t, checked=True):
    inertia, omega0, q0, t = common_float(inertia, omega0, q0, t, names=["inertia", "omega0", "q0", "t"])
    check_last_axis(inertia, 3, "inertia")
    check_last_axis(omega0, 3, "omega0")
    check_last_axis(q0, 4, "q0")
    check_batch_shapes(
        "torque_free_motion", ("inertia", inertia, 1), ("omega0", omega0, 1), ("q0", q0, 1), ("t", t, 0)
    )
    if checked:
        inertia, omega0, t = _checked(inertia, omega0, t, "torque_free_motion")
        q0 = check_rotation_quaternion(q0, "q0", "torque_free_motion")
    (inertia, omega0, q0), batch = _body_arrays(t, inertia, omega0, q0)
    return inertia, omega0, q0, t, batch


def torque_free_motion(
    inertia: Vector, omega0: Vector, q0: Quaternion, t: Scalar
) -> tuple[VectorOut, QuaternionOut]:
    """Body-frame angular velocity and orientation of a torque-free body at time ``t``, in closed form.

    Method (Landau & Lifshitz section 37, with the space axes along the conserved ``L``): with ``c`` the
    axis that ``omega`` circles, ``R(t) = R_L Rz(phi(t)) Rx(theta(t)) Rz(psi(t)) P``, where ``P`` relabels
    the body axes cyclically so that ``c`` is the third, ``theta`` and ``psi`` are the 3-1-3 angles of the
    body-frame unit momentum (exact from ``omega(t)``), ``R_L`` is constant (fixed by ``q0``) and

        dphi/dt = |L| (I_a w_a^2 + I_b w_b^2) / (I_a^2 w_a^2 + I_b^2 w_b^2)
                = (|L| / I_c) (1 + ((I_c - I_a) / I_a) / (1 + n sn^2(tau))),
        n = I_c (I_b - I_a) / (I_a (I_c - I_b)) >= 0,

    integrated in closed form: ``phi = (|L| / I_c) (t + (I_c - I_a)/I_a [G(tau(t)) - G(tau(0))] / (dtau/dt))``
    with ``G(tau) = Pi(-n; am(tau) | m)`` from Carlson's ``R_F`` and ``R_J`` (whole half-periods ``2 G(K)``
    plus reduced parts). The space-frame momentum ``R(t) I omega(t)`` is therefore constant to roundoff at
    any ``t``. Accuracy: an absolute error of a few ``eps * (|omega| t + precession angle per period)``
    (the first term is the conditioning of ``q`` in ``t``, the second that of the reduced third-kind
    integrals; ``G(tau) = Pi(-n; am tau | m)`` is within a few ulp of ``K(m)`` of mpmath's). For elongated
    bodies (``I_a << I_c``, where the precession rate peaks at ``|L| / I_a``) the error is larger than
    that: 3.3e-11 over 40 s for ``(1e-3, 1, 1.001)``, where an integrator at rtol 1e-11 reaches 3e-12
    (``tests/test_extreme_bodies.py``). Near the
    separatrix the integrals are measured from the nearest quarter period, so the accuracy holds for
    ``p = 1 - m`` down to the smallest normal number: at ``s = (L^2 - 2 E I_2) / L^2 = 1.5e-9`` and
    ``-4e-10``, ``q`` agrees with a 30-digit Taylor integration to 3e-15 and 1.5e-14 over a period (the
    motion itself amplifies input perturbations there, by ``~1/sqrt(|s|)`` per pass near the
    intermediate axis). Exactly on it (``p = 0``),
    ``G = (tau + sqrt(n) atan(sqrt(n) tanh tau)) / (1 + n)``. Symmetric bodies (``m = n = 0``) give the
    familiar rotation about ``L`` at ``|L| / I_1`` composed with the body spin, with no NaN as two moments
    meet (the derivative there is the one-sided, analytic one). Steady rotations (about a principal axis,
    the intermediate one included; any axis of a sphere; ``omega0 = 0``) return
    ``q0 (cos(|w| t/2), sin(|w| t/2) w/|w|)``; there the gradient of ``q`` is that of the steady rotation
    (finite, but not the sensitivity to a perturbation that starts a wobble), while that of ``omega`` is
    the flow's, as in :func:`torque_free_omega`.
    Elsewhere values and gradients (forward and reverse) are finite.

    **Arguments:**

    - `inertia`: principal moments ``(..., 3)`` in any order (kg m^2), as in
      :func:`torque_free_omega`.
    - `omega0`: angular velocity at ``t = 0`` in body-frame components (rad/s), ``(..., 3)``.
    - `q0`: orientation at ``t = 0``, a unit quaternion ``(w, x, y, z)`` mapping body-frame to
      space-frame components, ``(..., 4)``. A zero quaternion raises at run time.
    - `t`: time (s), broadcast against the bodies' batch axes as in :func:`torque_free_omega`.

    **Returns:** ``(omega, q)``: ``omega(t)`` (rad/s, body frame), shape ``batch + (3,)``, and the
    unit quaternion ``q(t)``, shape ``batch + (4,)``. ``q`` is continuous in ``t`` with
    ``q(0) = q0`` (the same sign as integrating ``dq/dt = q (0, omega) / 2``). Non-physical moments
    and NaN or inf inputs raise at run time.
    """
    return call_checked(_motion_program, _motion_failures, inertia, omega0, q0, t)


@eqx.filter_jit
def _motion_program(inertia, omega0, q0, t, *, checked):
    return _torque_free_motion(inertia, omega0, q0, t, checked=checked)


@eqx.filter_jit
def _motion_failures(inertia, omega0, q0, t):
    with collected_failures() as failures:
        _broadcast_motion_inputs(inertia, omega0, q0, t)
    return list(failures)


def _torque_free_motion(inertia, omega0, q0, t, *, checked):
    """:func:`torque_free_motion`; ``checked=False`` as in :func:`_torque_free_omega`."""
    inertia, omega0, q0, t, batch = _broadcast_motion_inputs(inertia, omega0, q0, t, checked)
    dtype = inertia.dtype
    steady = _steady(inertia, omega0)
    # A generic body stands in for steady ones, whose motion is below: no 0/0 in the general branch.
    inertia_g = jnp.where(steady[..., None], jnp.array([1.0, 2.0, 3.0], dtype), inertia)
    omega0_g = jnp.where(steady[..., None], jnp.array([1.0, 1.0, 1.0], dtype), omega0)
    omega_g, parts = _motion_parts(inertia_g, omega0_g, t)
    q_g = _general_orientation(inertia_g, omega0_g, omega_g, t, parts)
    q_g = _quat_multiply(q0, q_g)

    half = safe_norm(omega0) * t / 2
    # sin(|w| t/2) w/|w| as (t/2) sinc(|w| t/2) w: right value AND gradient at w = 0, where
    # d q/d w0 = q0 (0, t/2 I) (a body at rest turned by a small w0 turns by w0 t).
    vector = (t / 2 * jnp.sinc(half / jnp.pi))[..., None] * omega0
    q_s = _quat_multiply(q0, jnp.concatenate([jnp.cos(half)[..., None], vector], -1))
    omega = jnp.where(steady[..., None], _steady_omega(inertia, omega0, t, steady), omega_g)
    q = jnp.where(steady[..., None], q_s, q_g)
    return jnp.broadcast_to(omega, batch + (3,)), jnp.broadcast_to(q, batch + (4,))


def _general_orientation(inertia, omega0, omega_t, t, parts):
    """``q0* q(t)`` for a body that is not in steady rotation (see :func:`torque_free_motion`)."""
    perm, moments = parts["perm"], parts["moments"]
    around_largest, m, p, u = parts["around_largest"], parts["m"], parts["p"], parts["u"]
    del m
    I_a = jnp.where(around_largest, moments[..., 0], moments[..., 2])
    I_b = moments[..., 1]
    I_c = jnp.where(around_largest, moments[..., 2], moments[..., 0])
    n = _clip(_safe_div(I_c * (I_b - I_a), I_a * (I_c - I_b)), 0.0, jnp.inf)

    # The precession angle phi. K, G(K) and the start's reduced phase depend on the body only (they
    # keep its shape when t has more axes: computed once per body, not per sample time).
    (sn0, cn0, dn0), (sn1, cn1, dn1) = parts["start"], parts["now"]
    rho0, gamma0, am0, quarter = _reduced_phase(sn0, cn0, dn0, p, n)
    rho1, gamma1, am1, _ = _reduced_phase(sn1, cn1, dn1, p, n, quarter)
    quarter_f, quarter_g = quarter
    on_separatrix = p == 0
    quarter_f = jnp.where(on_separatrix, 1.0, quarter_f)
    turns = jnp.where(on_separatrix, 0.0, jnp.round((u + rho0 - rho1) / (2 * quarter_f)))
    delta_g = gamma1 - gamma0 + 2 * turns * jnp.where(on_separatrix, 0.0, quarter_g)
    # p = 0: G(tau) = tau / (1 + n) + sqrt(n) atan(sqrt(n) tanh(tau)) / (1 + n), tanh(tau) = sn.
    root_n = jnp.sqrt(jnp.where(on_separatrix, n, 1.0))
    delta_g_separatrix = (u + root_n * (jnp.arctan(root_n * sn1) - jnp.arctan(root_n * sn0))) / (1 + n)
    delta_g = jnp.where(on_separatrix, delta_g_separatrix, delta_g)
    delta_am = am1 - am0 + jnp.pi * turns
    speed = parts["speed"]
    size = safe_norm(inertia * omega0)
    phi = (size / I_c) * (t + (I_c - I_a) / I_a * delta_g / jnp.where(speed != 0, speed, 1.0))

    # Cyclic relabelling of the body axes: (x, y, c) = (c + 1, c + 2, c) mod 3, a proper rotation.
    c_index = jnp.take_along_axis(
        perm, jnp.where(around_largest, 2, 0)[..., None], axis=-1, mode="promise_in_bounds"
    )
    a_index = jnp.take_along_axis(
        perm, jnp.where(around_largest, 0, 2)[..., None], axis=-1, mode="promise_in_bounds"
    )[..., 0]
    to_cyclic = (c_index + jnp.arange(1, 4)) % 3
    from_cyclic = (jnp.arange(3) - c_index - 1) % 3
    l0 = jnp.take_along_axis(inertia * omega0, to_cyclic, axis=-1, mode="promise_in_bounds")
    l1 = _take(inertia * omega_t, to_cyclic)
    b0, psi0 = _nutation_spin_quat(l0)
    b1, psi1 = _nutation_spin_quat(l1)

    # psi is continuous in t; its principal values wrap. Relative to am(tau), psi = eps beta + const
    # with |beta - am| < pi/2 (beta the angle of (l_a, l_b)), eps = -1 when (x, y) = (a, b); the number
    # of wraps k flips the sign of the half-angle quaternion.
    eps = jnp.where(to_cyclic[..., 0] == a_index, -1.0, 1.0).astype(inertia.dtype)
    wraps = jnp.round((eps * delta_am - (psi1 - psi0)) / (2 * jnp.pi))
    flip = jnp.where(jnp.mod(wraps, 2) == 0, 1.0, -1.0).astype(inertia.dtype)

    zero = jnp.zeros_like(phi)
    precession = jnp.stack([jnp.cos(phi / 2), zero, zero, jnp.sin(phi / 2)], axis=-1)
    b0_conj = b0 * jnp.array([1.0, -1.0, -1.0, -1.0], inertia.dtype)
    q = _quat_multiply(b0_conj, _quat_multiply(precession, b1)) * flip[..., None]
    vector = _take(q[..., 1:], from_cyclic)
    return jnp.concatenate([q[..., :1], vector], axis=-1)


@eqx.filter_jit
def torque_free_orientation(inertia: Vector, omega0: Vector, q0: Quaternion, t: Scalar) -> QuaternionOut:
    """Orientation of a torque-free body at time ``t``: ``torque_free_motion(...)[1]``.

    Not re-exported: the public function is :func:`torque_free_motion`, which returns the
    orientation together with ``omega(t)``.
    """
    return torque_free_motion(inertia, omega0, q0, t)[1]
