"""Steady rotations of a torque-free body (a spin about a principal axis, any spin of a sphere, a
symmetric body spinning about an axis of its degenerate plane): the motion is ``omega0`` and a uniform
turn, and the derivatives are those of the linearised flow about it.

Along a steady rotation the variational equations have constant coefficients: with
``J = df/d omega`` and ``B = df/d inertia`` of Euler's equations ``omega' = f(omega, inertia)`` at
``omega0``, a perturbation ``(d omega0, d inertia)`` gives ``d omega(s) = exp(J s) d omega0 + int_0^s
exp(J r) dr B d inertia``. The orientation follows: ``q(t) = q_steady(t) exp(e(t) / 2)`` to first
order, with the body-frame error ``e' = d omega - omega0 x e``, ``e(0) = 0``. The value is the steady
motion exactly; the derivatives are formed only when derivatives are taken (custom JVPs).
"""

import jax
import jax.numpy as jnp

from .._kinematics.quaternion import _quat_multiply
from .._numerics import safe_norm_of
from .elliptic import _sin_cos


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
    in a degenerate plane. The value is ``omega0`` exactly. The flow matrices are only formed for
    derivatives (a custom JVP), for the steady bodies and those :func:`near_stable_axis`; other
    entries get harmless inputs there. The value costs nothing.
    """
    t = jnp.broadcast_to(t, jnp.broadcast_shapes(omega0.shape[:-1], jnp.shape(t)))
    return _linearised_flow(inertia, omega0, t, steady)


def _safe_inputs(inertia, omega0, steady):
    """``(inertia, omega0, mask)`` for the tangent maps, without their derivatives: the values of
    the steady bodies and of those near a stable axis (``mask``), a body at rest elsewhere."""
    inertia, omega0 = jax.lax.stop_gradient(inertia), jax.lax.stop_gradient(omega0)
    mask = steady | near_stable_axis(inertia, omega0)
    safe_w = jnp.where(mask[..., None], omega0, jnp.zeros_like(omega0))
    safe_i = jnp.where(mask[..., None], inertia, jnp.ones_like(inertia))
    return safe_i, safe_w, mask


@jax.custom_jvp
def _linearised_flow(inertia, omega, t, steady):
    """``omega`` at every time ``t`` (a steady rotation), whose tangent is the linearised flow."""
    return jnp.broadcast_to(omega, t.shape + (3,))


@_linearised_flow.defjvp
def _linearised_flow_jvp(primals, tangents):
    # The tangent of t does not enter: a steady rotation does not change with time. The primals are
    # constants of the tangent map (second derivatives along the steady rotation are not provided).
    inertia, omega, t, steady = primals
    d_inertia, d_omega, _, _ = tangents
    safe_i, safe_w, _ = _safe_inputs(inertia, omega, steady)
    flow, drive = _flow_matrices(safe_i, safe_w, jax.lax.stop_gradient(t))
    tangent = (flow @ d_omega[..., None])[..., 0] + (drive @ d_inertia[..., None])[..., 0]
    return _linearised_flow(*primals), tangent


def _flow_matrices(i_sg, w_sg, t_sg):
    """``exp(J t)`` and ``int_0^t exp(J s) ds B`` of :func:`_steady_omega`."""
    dtype = w_sg.dtype
    J, B = _euler_jacobians(i_sg, w_sg)
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


def _euler_jacobians(inertia, omega):
    """``J = df/d omega`` and ``B = df/d inertia`` of Euler's equations ``omega' = f(omega, inertia)``
    (principal moments), ``(..., 3, 3)`` each."""
    I1, I2, I3 = inertia[..., 0], inertia[..., 1], inertia[..., 2]
    w1, w2, w3 = omega[..., 0], omega[..., 1], omega[..., 2]
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
    return J, B


def near_stable_axis(inertia, omega0):
    """Bodies spinning within ``sqrt(eps)`` (relative) of the axis of their largest or smallest
    moment, but not exactly about it. Their elliptic form is exact in value, but its derivatives
    lose ``eps / offset`` of their size (the wobble's amplitude is the offset): 2.4e-4 at an offset
    of 1e-12, 32 times their size at 1e-17. The linearised motion's derivatives are within the
    offset of the motion's; the two errors meet near ``sqrt(eps)``. (About the intermediate axis the
    elliptic form's derivatives stay accurate: its motion is the separatrix's.)"""
    # Elementwise on the three components (no argmax and gather): it fuses with its neighbours.
    i1, i2, i3 = (inertia[..., k] for k in range(3))
    s1, s2, s3 = (omega0[..., k] * omega0[..., k] for k in range(3))
    total = s1 + s2 + s3
    off1, off2, off3 = s2 + s3, s1 + s3, s1 + s2
    off_largest = jnp.where((i1 >= i2) & (i1 >= i3), off1, jnp.where(i2 >= i3, off2, off3))
    off_smallest = jnp.where((i1 <= i2) & (i1 <= i3), off1, jnp.where(i2 <= i3, off2, off3))
    limit = jnp.finfo(omega0.dtype).eps * total
    return (total > 0) & (jnp.minimum(off_largest, off_smallest) < limit)


@jax.custom_jvp
def select_motion(general, steady_value, steady, inertia, omega0):
    """``where(steady, steady_value, general)`` (along the last axis), whose tangent is
    ``steady_value``'s for the steady bodies and those :func:`near_stable_axis`, ``general``'s
    elsewhere. The value is the plain selection, and the near-axis test is made only when
    derivatives are taken: the motion costs what it did without it."""
    return jnp.where(steady[..., None], steady_value, general)


@select_motion.defjvp
def _select_motion_jvp(primals, tangents):
    general, steady_value, steady, inertia, omega0 = primals
    d_general, d_steady = tangents[:2]
    mask = _safe_inputs(inertia, omega0, steady)[2]
    return select_motion(*primals), jnp.where(mask[..., None], d_steady, d_general)


def _steady_turn(inertia, omega0, t, steady):
    """The turn ``q0* q(t)`` of a steady rotation, ``(cos(|w| t/2), sin(|w| t/2) w/|w|)``, carrying the
    derivatives of the linearised motion (the module's docstring), and the half angle ``|w| t / 2``.
    Entries that are not ``steady`` get harmless inputs (a body at rest)."""
    t = jnp.broadcast_to(t, jnp.broadcast_shapes(omega0.shape[:-1], jnp.shape(t)))
    half = safe_norm_of(omega0[..., 0], omega0[..., 1], omega0[..., 2]) * t / 2
    return _linearised_turn(inertia, omega0, t, steady), half


def _uniform_turn(omega, t):
    half = safe_norm_of(omega[..., 0], omega[..., 1], omega[..., 2]) * t / 2
    # sin(|w| t/2) w/|w| as (t/2) sinc(|w| t/2) w: right value AND gradient at w = 0, where
    # d q/d w0 = q0 (0, t/2 I) (a body at rest turned by a small w0 turns by w0 t). sinc by its series
    # below 1e-3 (the next term is 2e-22).
    sin_h, cos_h = _sin_cos(half)
    small = jnp.abs(half) < 1e-3
    sinc = jnp.where(small, 1 - half * half / 6, sin_h / jnp.where(small, 1.0, half))
    return jnp.concatenate([cos_h[..., None], (t / 2 * sinc)[..., None] * omega], -1)


@jax.custom_jvp
def _linearised_turn(inertia, omega, t, steady):
    """:func:`_uniform_turn`, whose tangent is that of the linearised motion (for ``steady`` entries)."""
    return _uniform_turn(omega, t)


@_linearised_turn.defjvp
def _linearised_turn_jvp(primals, tangents):
    inertia, omega, t, steady = primals
    d_inertia, d_omega, d_t, _ = tangents
    turn = _uniform_turn(omega, t)
    shape = t.shape + (3, 3)
    safe_i, safe_w, mask = _safe_inputs(inertia, omega, steady)

    def maps():
        return _error_maps(safe_i, safe_w, jax.lax.stop_gradient(t))

    # Formed only where a batch holds a steady rotation or one near a stable axis (the common batch
    # holds none): a 9 x 9 matrix exponential per sample.
    m_omega, m_inertia = jax.lax.cond(
        jnp.any(mask), maps, lambda: (jnp.zeros(shape, t.dtype), jnp.zeros(shape, t.dtype))
    )
    # The body-frame error e of q = q_steady exp(e / 2), and the turn's own rate along t.
    error = (m_omega @ d_omega[..., None])[..., 0] + (m_inertia @ d_inertia[..., None])[..., 0]
    error = error + jax.lax.stop_gradient(omega) * d_t[..., None]
    d_turn = 0.5 * _quat_multiply(turn, jnp.concatenate([jnp.zeros_like(error[..., :1]), error], -1))
    return turn, d_turn


def _error_maps(inertia, omega, t):
    """``d e(t) / d omega0`` and ``d e(t) / d inertia`` of the body-frame error ``e`` of a steady
    rotation's orientation: the lower blocks of ``exp(A t)`` for the linear system
    ``(d omega, d inertia, e)' = A (d omega, d inertia, e)``,
    ``A = [[J, B, 0], [0, 0, 0], [1, 0, -[omega x]]]``. ``(..., 3, 3)`` each, broadcast with ``t``."""
    J, B = _euler_jacobians(inertia, omega)
    w1, w2, w3 = omega[..., 0], omega[..., 1], omega[..., 2]
    zero = jnp.zeros_like(w1)
    cross = jnp.stack(
        [jnp.stack([zero, -w3, w2], -1), jnp.stack([w3, zero, -w1], -1), jnp.stack([-w2, w1, zero], -1)], -2
    )
    blank = jnp.zeros_like(J)
    eye = jnp.broadcast_to(jnp.eye(3, dtype=J.dtype), J.shape)
    system = jnp.concatenate(
        [
            jnp.concatenate([J, B, blank], -1),
            jnp.concatenate([blank, blank, blank], -1),
            jnp.concatenate([eye, blank, -cross], -1),
        ],
        -2,
    )
    flow = _expm(system * t[..., None, None])
    return flow[..., 6:, :3], flow[..., 6:, 3:6]


TAYLOR_DEGREE = 18
"""Terms of the series of :func:`_expm` after scaling to a 1-norm of at most 1: the remainder is
below ``1 / 19! = 8e-18``."""


def _expm(matrix):
    """``exp(matrix)`` of ``(..., n, n)`` matrices: scaled by ``2^-s`` to a 1-norm of at most 1, the
    Taylor series by Horner's rule, squared ``s`` times. Two loops of small bodies: the derivative
    program of the free body's motion compiled no slower with it (within the 0.5 s run-to-run
    spread), where ``jax.scipy.linalg.expm`` (Pade approximants of five orders) added 1.1 s to 5.3 s."""
    norm = jnp.max(jnp.sum(jnp.abs(matrix), axis=-2), axis=-1)
    squarings = jnp.clip(jnp.ceil(jnp.log2(jnp.maximum(norm, 1e-300))), 0.0, 64.0)
    scaled = matrix * jnp.exp2(-squarings)[..., None, None]
    eye = jnp.broadcast_to(jnp.eye(matrix.shape[-1], dtype=matrix.dtype), matrix.shape)

    def horner(k, series):
        return eye + scaled @ series / (TAYLOR_DEGREE - k).astype(matrix.dtype)

    series = jax.lax.fori_loop(0, TAYLOR_DEGREE, horner, eye)

    def square(k, power):
        return jnp.where((k.astype(squarings.dtype) < squarings)[..., None, None], power @ power, power)

    return jax.lax.fori_loop(0, jnp.max(squarings).astype(jnp.int32), square, series)
