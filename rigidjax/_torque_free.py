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
``omega0`` unchanged.
"""

import jax.numpy as jnp

from ._elliptic import ellipj_m1, ellipkm1
from ._misc import check_last_axis, common_float
from ._types import Scalar, ScalarOut, Vector, VectorOut


def _sorted_frame(inertia, omega0):
    """Moments ascending, omega permuted alike, and the permutation's parity (+1 even, -1 odd)."""
    perm = jnp.argsort(inertia, axis=-1)
    moments = jnp.take_along_axis(inertia, perm, axis=-1)
    omega = jnp.take_along_axis(omega0, perm, axis=-1)
    p0, p1, p2 = perm[..., 0], perm[..., 1], perm[..., 2]
    inversions = sum((x > y).astype(jnp.int32) for x, y in ((p0, p1), (p0, p2), (p1, p2)))
    parity = jnp.where(inversions % 2 == 0, 1.0, -1.0).astype(inertia.dtype)
    return perm, moments, omega, parity


def _momentum_defect(moments, x, j):
    """``L^2 - 2 E I_j`` written without cancellation: ``sum_i I_i (I_i - I_j) omega_i^2``."""
    return sum(moments[..., i] * (moments[..., i] - moments[..., j]) * x[..., i] for i in range(3) if i != j)


def _safe_div(num, den):
    ok = den != 0
    return jnp.where(ok, num / jnp.where(ok, den, 1.0), 0.0)


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
    m = jnp.clip(_safe_div((Ib - Ia) * -Dc, (Ic - Ib) * Da), 0.0, 1.0)
    p = jnp.clip(_safe_div((Ic - Ia) * Db, (Ic - Ib) * Da), 0.0, 1.0)
    return around_largest, (amp_a, amp_b, amp_c), rate, m, p


def torque_free_omega(inertia: Vector, omega0: Vector, t: Scalar) -> VectorOut:
    """Body-frame angular velocity of a torque-free body at time ``t`` (s) after ``omega0`` (rad/s).

    ``inertia`` are principal moments ``(..., 3)`` in any order (kg m^2); ``t`` broadcasts against
    the batch axes (for a batch of bodies at T times use ``inertia[:, None]``, ``omega0[:, None]``,
    ``ts[None, :]``). Exact up to roundoff: no integration, so the cost does not grow with ``t``.
    """
    inertia, omega0, t = common_float(inertia, omega0, t, names=["inertia", "omega0", "t"])
    check_last_axis(inertia, 3, "inertia")
    check_last_axis(omega0, 3, "omega0")
    batch = jnp.broadcast_shapes(inertia.shape[:-1], omega0.shape[:-1], t.shape)
    inertia = jnp.broadcast_to(inertia, batch + (3,))
    omega0 = jnp.broadcast_to(omega0, batch + (3,))
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
    sn, cn, dn, _ = ellipj_m1(u, p)
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
    return jnp.take_along_axis(sorted_out, jnp.argsort(perm, axis=-1), axis=-1)


def torque_free_period(inertia: Vector, omega0: Vector) -> ScalarOut:
    """Period of the body-frame angular velocity of a torque-free body, ``4 K(m) / lambda`` (s).

    Half of it is the time between two tennis-racket flips (omega_b changes sign every ``2K/lambda``).
    Infinite on the separatrix and for steady rotation (``lambda = 0``).
    """
    inertia, omega0 = common_float(inertia, omega0, names=["inertia", "omega0"])
    check_last_axis(inertia, 3, "inertia")
    check_last_axis(omega0, 3, "omega0")
    inertia, omega0 = jnp.broadcast_arrays(inertia, omega0)
    _, moments, omega, _ = _sorted_frame(inertia, omega0)
    _, _, rate, _, p = _solution_parameters(moments, omega)
    quarter = ellipkm1(jnp.where(p > 0, p, 1.0))
    return jnp.where((rate > 0) & (p > 0), 4.0 * quarter / jnp.where(rate > 0, rate, 1.0), jnp.inf)
