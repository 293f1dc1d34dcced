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
import numpy as np

from .._checks import (
    call_checked,
    check_batch_shapes,
    check_finite,
    check_last_axis,
    check_unit_quaternion,
    collected_failures,
    common_float,
    error_if,
    is_tensor_shape,
    known_values,
    packed_failures,
)
from .._dynamics.inertia import check_inertia
from .._kinematics.quaternion import _quat_multiply
from .._types import Quaternion, QuaternionOut, Scalar, ScalarOut, Vector, VectorOut
from .barrier import _held_per_body, _materialised
from .carlson import _carlson_rf_rd
from .derivatives import sample_jacobians
from .elliptic import _ellipj_checked, ellipkm1
from .frame import (
    PHASE_ROUNDING_LIMIT,
    _safe_div,
    _solution_parameters,
    _sorted_frame,
    _unsort,
    largest_phase,
    phase_advice,
    phase_unresolved,
    unit_scaled,
)
from .precession import _general_orientation
from .steady import _steady_omega, _steady_turn, select_motion


def _checked(inertia, omega0, t, where):
    """Run-time value checks of the public closed forms (``eqx.error_if``: also under jit/vmap)."""
    # Principal moments, per body: check_inertia would read a trailing (3, 3) as ONE tensor, and a
    # diagonal tensor passed here (three "bodies" with zero moments) then ran as steady rotations.
    name = f"{where}: inertia"
    if is_tensor_shape(inertia.shape):
        name += (
            " (principal moments (..., 3): a trailing (3, 3) is three bodies' moments here, not a "
            "tensor; diagonalise a tensor with rigidjax.principal_axes)"
        )
    inertia = check_inertia(inertia[..., None, :], name=name)[..., 0, :]
    omega0 = check_finite(omega0, "omega0", where)
    # The closed form is finite exactly where |L|^2 and 2E of the moments it computes with (scaled so
    # that the largest is below 1, unit_scaled) are (float64: NaN from |I omega| ~ 1.3e154 on, where
    # |L|^2 overflows): beyond, finite inputs gave NaN without an error.
    scaled = unit_scaled(inertia)
    momentum2 = jnp.sum((scaled * omega0) ** 2, axis=-1)
    energy2 = jnp.sum(scaled * omega0 * omega0, axis=-1)
    omega0 = error_if(
        omega0,
        jnp.isfinite(inertia).all(-1) & jnp.isfinite(omega0).all(-1) & ~jnp.isfinite(momentum2 + energy2),
        f"{where}: the angular momentum of inertia and omega0 is beyond the range of {omega0.dtype} "
        "(|I omega|^2 overflows, with the moments scaled so that the largest is below 1), where the "
        "closed form cannot be evaluated: express omega0 in units that make it smaller.",
    )
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


def _frame(inertia, omega0, held=True):
    """The sorted frame (:func:`_sorted_frame`), which bodies rotate steadily, and in the sorted frame a
    generic body that stands in for those: the elliptic parametrisation is singular there (its
    amplitudes are square roots of zero), and their motion and derivatives come from
    :func:`_steady_omega` instead.

    Steady: rotation about a fixed body axis, i.e. a principal axis, any axis of a sphere, one in the
    degenerate plane of a symmetric body (``rate = 0``), or ``omega0 = 0``. ``held``: the sorted
    moments and omega held in memory (:mod:`.barrier`), for callers that read them at many times.
    """
    swaps, index, moments, omega, parity = _sorted_frame(inertia, omega0)
    rate = _solution_parameters(moments, omega)[2]
    zeros = sum((w == 0).astype(jnp.int32) for w in omega)
    steady = (rate == 0) | (zeros >= 2)
    moments = [jnp.where(steady, float(k + 1), i) for k, i in enumerate(moments)]
    omega = [jnp.where(steady, 1.0, w) for w in omega]
    if held:  # read by many kernels, each of which would sort the axes again
        kept = _materialised((*moments, *omega, parity))
        moments, omega, parity = list(kept[:3]), list(kept[3:6]), kept[6]
    return dict(swaps=swaps, index=index, moments=moments, omega=omega, parity=parity, steady=steady)


def _start(frame):
    """The elliptic parameters of the body in the sorted frame, the Jacobi functions of its initial
    phase (read off ``omega0`` directly) and the signed rate ``speed`` of its elliptic argument."""
    moments, omega, parity = frame["moments"], frame["omega"], frame["parity"]
    around_largest, (amp_a, amp_b, amp_c), rate, m, p, nu = _solution_parameters(moments, omega)
    w_a = jnp.where(around_largest, omega[0], omega[2])
    w_b = omega[1]
    w_c = jnp.where(around_largest, omega[2], omega[0])
    sign_c = jnp.where(w_c < 0, -1.0, 1.0).astype(w_c.dtype)
    # amp_a and amp_b vanish together (pure spin about axis c): phase 0, so that cn0^2 + sn0^2 = 1.
    cn0 = jnp.where(amp_a > 0, w_a / jnp.where(amp_a > 0, amp_a, 1.0), 1.0)
    sn0 = _safe_div(w_b, amp_b)
    dn0 = jnp.where(amp_c > 0, jnp.abs(w_c) / jnp.where(amp_c > 0, amp_c, 1.0), 1.0)
    # The sign of d(tau)/dt follows the sense of rotation about axis c; an odd relabelling of the
    # body axes reverses it (it flips the cross product in Euler's equations).
    speed = parity * sign_c * rate
    return dict(
        around_largest=around_largest,
        amplitudes=(amp_a, amp_b, amp_c),
        m=m,
        p=p,
        nu=nu,
        speed=speed,
        sign_c=sign_c,
        start=(sn0, cn0, dn0),
        omega_start=(w_a, w_b, w_c),
    )


def _motion_parts(frame, t, held=False):
    """The elliptic solution at ``t`` in the body's axes, and in the sorted frame the pieces the
    orientation reuses. ``held``: its components computed in full before they are stacked (see
    :mod:`.barrier`; omega alone: 10^4 bodies 7.2 -> 5.5 ms, not with the orientation, which
    reads them)."""
    first = _start(frame)
    # Per body and read at every sample: held where there are several samples a body, or each
    # sample's kernels derived the elliptic parameters from the frame again.
    leaves, tree = jax.tree.flatten(first)
    first = jax.tree.unflatten(tree, _held_per_body(leaves, t))
    around_largest, (amp_a, amp_b, amp_c) = first["around_largest"], first["amplitudes"]
    m, p, sign_c = first["m"], first["p"], first["sign_c"]
    sn0, cn0, dn0 = first["start"]
    u = first["speed"] * t
    sn, cn, dn, _ = _ellipj_checked(u, 1 - p, p)  # the AGM of p stays per body
    sn, cn, dn = _materialised((sn, cn, dn))  # read by every component of omega and q
    # = 1 - m sn^2 sn0^2, written without its cancellation when sn and sn0 are both near 1 (the
    # separatrix, where m = 1).
    denominator = cn0 * cn0 + sn0 * sn0 * dn * dn
    sn_t = (sn * cn0 * dn0 + sn0 * cn * dn) / denominator
    cn_t = (cn * cn0 - sn * sn0 * dn * dn0) / denominator
    dn_t = (dn * dn0 - m * sn * sn0 * cn * cn0) / denominator
    out_a, out_b, out_c = amp_a * cn_t, amp_b * sn_t, sign_c * amp_c * dn_t
    if held:
        out_a, out_b, out_c = _materialised((out_a, out_b, out_c))
    sorted_out = [jnp.where(around_largest, out_a, out_c), out_b, jnp.where(around_largest, out_c, out_a)]
    omega_t = _unsort(jnp.stack(sorted_out, axis=-1), frame["index"])
    return omega_t, {**first, "u": u, "omega_now": (out_a, out_b, out_c)}


def torque_free_omega(inertia: Vector, omega0: Vector, t: Scalar) -> VectorOut:
    """Body-frame angular velocity of a torque-free body at time ``t``, in closed form.

    The solution in Jacobi elliptic functions (Landau & Lifshitz, section 37), on both sides of the
    separatrix.
    Exact up to roundoff: no integration, so the cost does not grow with ``t``. The roundoff does:
    an absolute error of about ``eps`` times the elliptic argument ``lambda t`` (float32, moments
    ``(1, 2, 3)``, 1 rad/s in random directions, against float64: a median 1.5e-7 and at most
    7e-7 at ``t = 10`` s, a median 1e-5 and at most 2e-4 at 10^3 s). A phase rounded by more than
    1e-3 rad (float64: 4.5e12 rad, float32: 8.4e3 rad) is a ``ValueError`` naming the sample (a
    run-time error under ``jit``).

    Derivatives (forward and reverse) are those of the flow and finite everywhere, steady rotations
    included (spin about any principal axis, a sphere: there ``d omega(t) / d omega0 = exp(J t)`` grows
    like ``cosh(lambda t)`` about the intermediate axis). The derivative with respect to ``inertia``
    loses about ``eps / gap`` relative accuracy as the moments meet (``gap`` the relative difference of
    two moments; measured 6e-3 at ``gap = 1e-15``, 1e-8 at 1e-9, 7e-12 at 1e-6,
    ``tests/test_extreme_bodies.py``): the parametrisation's ``1 / (I_j - I_k)`` terms cancel. Exactly
    equal moments are exact; for gaps below ~1e-9 differentiate ``simulate`` instead.

    **Arguments:**

    - `inertia`: principal moments ``(..., 3)`` in any order (kg m^2); a trailing ``(3, 3)`` is three
      bodies' moments, not a tensor. Non-physical moments (beyond
      the flat plate, non-positive) are an error at run time.
    - `omega0`: angular velocity at ``t = 0`` in body-frame components (rad/s), ``(..., 3)``.
    - `t`: time (s), broadcast against the batch axes of `inertia` and `omega0`: for a batch of
      bodies at T times use ``inertia[:, None]``, ``omega0[:, None]``, ``ts[None, :]``.

    **Returns:** ``omega(t)`` in body-frame components (rad/s), shape ``batch + (3,)`` with ``batch``
    the broadcast of the bodies' batch axes with ``t``'s shape. NaN or inf in any input raises at run
    time.
    """
    omega, phase = call_checked(
        _omega_program, _omega_failures, inertia, omega0, t, names=("inertia", "omega0", "t")
    )
    return _raise_if_unresolved(omega, phase, "torque_free_omega")


# One compiled program per shape (eager calls would dispatch op by op). Inputs with values are checked
# by a program of their own that returns the failed conditions (a ValueError is raised from them), so
# neither program holds a host callback and JAX's persistent cache keeps both: a new process compiles
# nothing. Inputs without values (the user's jit or vmap) get eqx.error_if checks in the program.
@eqx.filter_jit
def _omega_program(inertia, omega0, t, *, checked):
    omega, phase = _torque_free_omega(inertia, omega0, t, checked=checked, phases=True)
    return _phase_checked(omega, phase, t)


def _phase_checked(result, phase, t):
    """``result`` and its largest phase (``phase``: per sample, :func:`.largest_phase`) with the
    sample's time and index, for :func:`_raise_if_unresolved`."""
    if phase.size == 0:
        return result, None
    index = jnp.argmax(jnp.ravel(phase))
    at = jnp.ravel(jnp.broadcast_to(t, phase.shape))[index]
    element = jnp.stack(jnp.unravel_index(index, phase.shape)) if phase.ndim else jnp.zeros(0, jnp.int32)
    return result, (jnp.ravel(phase)[index], at, element)


def _raise_if_unresolved(result, phase, where):
    """``result``, or a ``ValueError`` naming the sample with the largest phase (``phase`` from
    :func:`_phase_checked`) if it is beyond what the dtype resolves. Without values (the user's
    ``jit``, also around a call whose inputs are its constants) a run-time error."""
    if phase is None:
        return result
    values = known_values(phase)
    if values is None:
        largest = phase[0]
        return error_if(
            result,
            phase_unresolved(largest),
            f"{where}: a phase of the closed form is beyond what {largest.dtype} resolves (its rounding "
            f"exceeds {PHASE_ROUNDING_LIMIT:g} rad): the result would be noise. "
            + phase_advice(largest.dtype, "t = 0"),
        )
    largest, at, index = (np.asarray(v) for v in values)
    if not phase_unresolved(largest):
        return result
    element = f" (element {tuple(index.tolist())} of the broadcast batch)" if index.size else ""
    raise ValueError(
        f"{where}: at t = {float(at):.6g} s{element} the closed form's phase is {float(largest):.3g} rad, "
        f"which {largest.dtype} holds only to {float(largest) * float(np.finfo(largest.dtype).eps):.3g} "
        f"rad (more than {PHASE_ROUNDING_LIMIT:g} rad): the result would be noise. "
        + phase_advice(largest.dtype, "t = 0")
    )


@eqx.filter_jit
def _omega_failures(inertia, omega0, t):
    with collected_failures() as failures:
        _broadcast_inputs(inertia, omega0, t)
    return packed_failures(failures)


def _torque_free_omega(inertia, omega0, t, *, checked, phases=False):
    """:func:`torque_free_omega`; ``checked=False`` leaves out its run-time value checks (equinox
    errors, host callbacks: JAX's persistent cache keeps no program that holds one) for callers
    whose values are valid by construction, such as the fit's parametrised moments. ``phases``: also
    return the size of the elliptic argument at each sample (:func:`.largest_phase`; 0 for steady
    rotations, whose omega is omega0)."""
    inertia, omega0, t, batch = _broadcast_inputs(inertia, omega0, t, checked)
    inertia = unit_scaled(inertia)
    frame = _frame(inertia, omega0)
    steady = frame["steady"]
    omega_g, parts = _motion_parts(frame, t, held=True)
    omega_s = _steady_omega(inertia, omega0, t, steady)
    omega = jnp.broadcast_to(select_motion(omega_g, omega_s, steady, inertia, omega0), batch + (3,))
    if not phases:
        return omega
    return omega, jnp.broadcast_to(jnp.where(steady, 0.0, largest_phase(parts["u"])), batch)


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
    return call_checked(_period_program, _period_failures, inertia, omega0, names=("inertia", "omega0"))


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
    return packed_failures(failures)


@eqx.filter_jit
def _period_program(inertia, omega0, *, checked):
    return _period_and_quarter(*_period_inputs(inertia, omega0, checked))[0]


def motion_timing(inertia, omega0):
    """When a torque-free body flips: its period (:func:`torque_free_period`) and the time to its
    next half period's start (the intermediate component's next sign change), from principal
    moments and omega of the same shape ``(..., 3)``, without checks; inf and 0 where the body does
    not flip (steady rotations, the separatrix).

    The phase of the start is ``F(a | m)``, ``a`` its elliptic amplitude forward in time modulo
    ``pi``; the next flip comes after ``(2 K - F) / lambda``, i.e. ``1 - F / (2 K)`` of the half
    period. ``K = R_F(0, 1 - m, 1)`` and ``F`` share one Carlson loop, and the amplitude enters only
    through ``sn`` and ``cn`` of the start (no trigonometric functions): simulate compiles this into
    every torque-free program to order its bodies. For ordering bodies: not differentiable."""
    # Evaluated once per body: no sample times read the frame, and each array held in memory is a
    # kernel of its own in every torque-free program simulate compiles (16 of 44 here).
    frame = _frame(unit_scaled(inertia), omega0, held=False)
    first = _start(frame)
    moving = ~frame["steady"] & (first["p"] > 0)
    p = jnp.where(moving, first["p"], 0.5)
    rate = jnp.where(moving, jnp.abs(first["speed"]), 1.0)
    sn0, cn0, _ = first["start"]
    # a = j pi + r with |r| <= pi / 2: cos r = |cn0| and sin r = +-sin a, the sign that makes cos r >= 0;
    # a lies in (pi / 2, pi) (j = 1) where sin a and cos a differ in sign.
    sin_a = jnp.where(first["speed"] < 0, -sn0, sn0)
    sin_r = jnp.where(cn0 < 0, -sin_a, jnp.where(cn0 > 0, sin_a, jnp.abs(sin_a)))
    cos_r2 = cn0 * cn0
    upper = sin_a * cn0 < 0
    x = jnp.stack([jnp.zeros_like(p), cos_r2])
    y = jnp.stack([p, cos_r2 + p * sin_r * sin_r])
    rf = _carlson_rf_rd(x, y, jnp.ones_like(x), with_rd=False)[0]
    quarter, phase = rf[0], sin_r * rf[1] + jnp.where(upper, 2.0 * rf[0], 0.0)
    period = 4.0 * quarter / rate
    next_flip = (1.0 - phase / (2.0 * quarter)) * period / 2
    return jnp.where(moving, period, jnp.inf), jnp.where(moving, next_flip, 0.0)


def _period_and_quarter(inertia, omega0):
    """:func:`torque_free_period` of principal moments and omega of the same shape ``(..., 3)``,
    without checks, and the quarter period ``K(m)`` of the elliptic argument (that of a generic
    body where the motion is steady)."""
    _, _, moments, omega, _ = _sorted_frame(unit_scaled(inertia), omega0)
    rate = _solution_parameters(moments, omega)[2]
    # rate = 0 (a sphere, a symmetric body in steady rotation): the period is infinite; a generic
    # body stands in so that the square roots of zero do not make the gradient NaN.
    still = rate == 0
    moments = [jnp.where(still, float(k + 1), i) for k, i in enumerate(moments)]
    omega = [jnp.where(still, 1.0, w) for w in omega]
    _, _, rate, _, p, _ = _solution_parameters(moments, omega)
    quarter = ellipkm1(jnp.where(p > 0, p, 1.0))
    return jnp.where(~still & (p > 0), 4.0 * quarter / rate, jnp.inf), quarter


# --------------------------------------------------------------------------------------------------
# Steady rotations and the motion (the precession angle: .precession)


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
        q0 = check_unit_quaternion(q0, "q0", "torque_free_motion")
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
    with ``G(tau) = Pi(-n; am(tau) | m)`` from Jacobi's theta-function form of the integral of the third
    kind (a rate times ``t`` plus the bounded phase of a theta function at ``tau + i beta``, see
    :func:`_precession_parts`). The space-frame momentum ``R(t) I omega(t)`` is therefore constant to
    roundoff at any ``t``. Accuracy: an absolute error of a few ``eps * (|omega| t + precession angle per
    period)`` (the first term is the conditioning of ``q`` in ``t``, the second that of the third-kind
    integral; ``G(tau) = Pi(-n; am tau | m)`` is within a few ulp of ``K(m)`` of mpmath's). Thin rods
    circling their long axis (``I_c << I_a``, ``g -> 1``) keep it: the rate is formed as
    ``|L| (g / I_a + (1 - g) / I_c)`` with ``1 - g`` computed directly, not by cancelling ``|L| / I_c``;
    over 40 s ``q`` agrees with a 30-digit Taylor integration to 1.4e-14 for ``(1e-3, 1, 1.001)`` and
    1.7e-14 for ``(1e-9, 1, 1 + 5e-10)``, and float32 rods down to ``I_1 = 1e-9`` stay within 1e-5.
    Near the separatrix the initial phase is measured from the nearest
    quarter period, so the accuracy holds for ``p = 1 - m`` down to the smallest normal number: at
    ``s = (L^2 - 2 E I_2) / L^2 = 1.5e-9`` and ``-4e-10``, ``q`` agrees with a 30-digit Taylor integration
    to 3e-15 and 1.5e-14 over a period (the motion itself amplifies input perturbations there, by
    ``~1/sqrt(|s|)`` per pass near the intermediate axis). Exactly on it (``p = 0``) the same formulas
    give ``G = (tau + sqrt(n) atan(sqrt(n) tanh tau)) / (1 + n)``.
    Symmetric bodies (``m = n = 0``) give the
    familiar rotation about ``L`` at ``|L| / I_1`` composed with the body spin, with no NaN as two moments
    meet (the derivative there is the one-sided, analytic one). Steady rotations (about a principal axis,
    the intermediate one included; any axis of a sphere; ``omega0 = 0``) return
    ``q0 (cos(|w| t/2), sin(|w| t/2) w/|w|)``; there the derivatives of ``omega`` and ``q`` are those
    of the linearised motion (the flow ``exp(J t)`` of Euler's equations and the orientation error it
    drives), the sensitivity to a perturbation that starts a wobble, as an integrator's derivative
    gives it. Elsewhere values and gradients (forward and reverse) are finite.

    **Arguments:**

    - `inertia`: principal moments ``(..., 3)`` in any order (kg m^2), as in
      :func:`torque_free_omega`.
    - `omega0`: angular velocity at ``t = 0`` in body-frame components (rad/s), ``(..., 3)``.
    - `q0`: orientation at ``t = 0``, a unit quaternion ``(w, x, y, z)`` mapping body-frame to
      space-frame components, ``(..., 4)``; one further than roundoff from unit norm raises at
      run time (as in :func:`rigidjax.simulate`: normalise it with :func:`rigidjax.quat_normalize`).
    - `t`: time (s), broadcast against the bodies' batch axes as in :func:`torque_free_omega`.

    **Returns:** ``(omega, q)``: ``omega(t)`` (rad/s, body frame), shape ``batch + (3,)``, and the
    unit quaternion ``q(t)``, shape ``batch + (4,)``. ``q`` is continuous in ``t`` with
    ``q(0) = q0`` (the same sign as integrating ``dq/dt = q (0, omega) / 2``). Non-physical moments
    and NaN or inf inputs raise at run time, as does a sample whose phase (the elliptic argument, the
    precession angle, a steady rotation's angle) is rounded by more than 1e-3 rad, as in
    :func:`torque_free_omega`.
    """
    motion, phase = call_checked(
        _motion_program, _motion_failures, inertia, omega0, q0, t, names=("inertia", "omega0", "q0", "t")
    )
    return _raise_if_unresolved(motion, phase, "torque_free_motion")


@eqx.filter_jit
def _motion_program(inertia, omega0, q0, t, *, checked):
    *motion, phase = _torque_free_motion(inertia, omega0, q0, t, checked=checked, phases=True)
    return _phase_checked(tuple(motion), phase, t)


@eqx.filter_jit
def _motion_failures(inertia, omega0, q0, t):
    with collected_failures() as failures:
        _broadcast_motion_inputs(inertia, omega0, q0, t)
    return packed_failures(failures)


def _torque_free_motion(inertia, omega0, q0, t, *, checked, phases=False):
    """:func:`torque_free_motion`; ``checked=False`` and ``phases`` as in :func:`_torque_free_omega`
    (the phases of the orientation included)."""
    inertia, omega0, q0, t, batch = _broadcast_motion_inputs(inertia, omega0, q0, t, checked)
    omega, turn, phase = _motion_core(inertia, omega0, jnp.broadcast_to(t, batch))
    motion = jnp.broadcast_to(omega, batch + (3,)), _quat_multiply(q0, turn)
    return (*motion, phase[..., 0]) if phases else motion


def _motion_at(inertia, omega0, t):
    """``omega(t)``, the rotation ``q0* q(t)`` and the size of their phases (:func:`.largest_phase`,
    ``batch + (1,)``) of bodies whose arrays are broadcast (:func:`_body_arrays`), ``t`` of the batch's
    shape."""
    inertia = unit_scaled(inertia)
    frame = _frame(inertia, omega0)
    steady = frame["steady"]
    omega_g, parts = _motion_parts(frame, t)
    turn_g, precession = _general_orientation(frame, parts, t)

    turn_s, half = _steady_turn(inertia, omega0, t, steady)
    omega = select_motion(omega_g, _steady_omega(inertia, omega0, t, steady), steady, inertia, omega0)
    turn = select_motion(turn_g, turn_s, steady, inertia, omega0)
    phase = jnp.where(steady, largest_phase(half), largest_phase(parts["u"], precession))
    return omega, turn, phase[..., None]


# With the orientation, reverse mode transposes the contraction of every sample's Jacobian (see
# .derivatives): 14 ms against 651 ms for 10^3 bodies at one time, 8.9 against 31 ms for 45 bodies at
# 120 times. omega alone (_torque_free_omega) is differentiated as it is computed: its reverse mode is
# cheap (4.5 and 3.0 ms there, against 2.4 and 7.8 ms by every sample's Jacobian).
_motion_core = sample_jacobians(_motion_at, (3, 3, 0))


@eqx.filter_jit
def torque_free_orientation(inertia: Vector, omega0: Vector, q0: Quaternion, t: Scalar) -> QuaternionOut:
    """Orientation of a torque-free body at time ``t``: ``torque_free_motion(...)[1]``.

    Not re-exported: the public function is :func:`torque_free_motion`, which returns the
    orientation together with ``omega(t)``.
    """
    return torque_free_motion(inertia, omega0, q0, t)[1]
