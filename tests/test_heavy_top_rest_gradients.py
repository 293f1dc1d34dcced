"""Derivatives with respect to ``omega0`` of the exact heavy top (``simulate(HeavyTop, accuracy="exact")``)
where ``w3 = 0`` and ``L_z = 0``: released from rest at a tilt, swinging in a vertical plane through the
pivot (below and over the top), hanging at rest; and with respect to the tilt of ``q0`` for a top started
exactly at a pole with a wobble, or at a pole up to the rounding of ``q0``. A Cayley-Klein half has
``b + k a = 0`` there (or within rounding of it).

Reference: central differences of scipy's DOP853 (rtol 1e-12) on Euler's equations with the gravity
torque and the quaternion kinematics, written below in numpy.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.integrate import solve_ivp

import rigidjax as rj

INERTIA = np.array([1e-2, 1e-2, 5e-3])
MASS, COM_Z, G = 0.5, 0.05, 9.81
STEP = 1e-6  # central differences


def reference(omega0, q0, t):
    """``(omega, q)`` at ``t`` by DOP853: ``I w' = (I w) x w + (R^T Z) x (m g com)``, ``q' = q (0, w) / 2``
    (``R^T Z`` the space vertical in the body frame)."""
    a, _, c = INERTIA
    weight = MASS * G * COM_Z

    def rhs(_, y):
        w1, w2, w3, qw, qx, qy, qz = y.tolist()
        # R^T Z and the torque com x (-m g R^T Z).
        e1, e2 = 2 * (qx * qz - qw * qy), 2 * (qy * qz + qw * qx)
        t1, t2 = weight * e2, -weight * e1
        return [
            ((a - c) * w2 * w3 + t1) / a,
            ((c - a) * w1 * w3 + t2) / a,
            0.0,
            0.5 * (-qx * w1 - qy * w2 - qz * w3),
            0.5 * (qw * w1 + qy * w3 - qz * w2),
            0.5 * (qw * w2 - qx * w3 + qz * w1),
            0.5 * (qw * w3 + qx * w2 - qy * w1),
        ]

    y0 = np.concatenate([omega0, q0])
    sol = solve_ivp(rhs, (0.0, t), y0, method="DOP853", rtol=1e-12, atol=1e-14)
    return sol.y[:, -1]


def turned(q0, tilt):
    """``q0`` turned by the small body-frame rotation ``(tilt_x, tilt_y, 0)``: ``q0 (1, tilt / 2)``,
    normalised."""
    w, x, y, z = q0[0], q0[1], q0[2], q0[3]
    tx, ty = tilt[0] / 2, tilt[1] / 2
    q = [w - x * tx - y * ty, x + w * tx - z * ty, y + w * ty + z * tx, z + x * ty - y * tx]
    norm = (q[0] ** 2 + q[1] ** 2 + q[2] ** 2 + q[3] ** 2) ** 0.5
    return [c / norm for c in q]


def reference_jacobian(omega0, q0, t):
    """Central differences in ``omega0`` (3 columns) and in the tilt of ``q0`` (2 columns)."""
    columns = []
    for e in np.eye(5):
        plus, minus = (
            reference(omega0 + sign * STEP * e[:3], np.array(turned(q0, sign * STEP * e[3:])), t)
            for sign in (1, -1)
        )
        columns.append((plus - minus) / (2 * STEP))
    return np.stack(columns, axis=1)


def final_state(omega0, tilt, q0, t):
    """``(omega, q)`` at ``t`` from ``omega0`` and ``q0`` turned by ``tilt``, concatenated: one program for
    every case (``q0`` and ``t`` are inputs)."""
    top = rj.HeavyTop(inertia=jnp.asarray(INERTIA), mass=MASS, com=jnp.array([0.0, 0.0, COM_Z]))
    state = rj.State(omega=omega0, orientation=jnp.stack(turned(q0, tilt)))
    traj = rj.simulate(top, state, jnp.stack([0.0 * t, t]), accuracy="exact")
    return jnp.concatenate([traj.omega[-1], traj.orientation[-1]])


WEIGHTS = np.array([0.2, -0.5, 0.7, 0.3, -0.2, 0.5, 0.9])
# With respect to omega0 and the tilt (and the value).
_jacfwd = jax.jit(jax.jacfwd(lambda *args: (final_state(*args),) * 2, argnums=(0, 1), has_aux=True))
_grad = jax.jit(jax.grad(lambda *args: jnp.dot(final_state(*args), WEIGHTS), argnums=(0, 1)))
NO_TILT = jnp.zeros(2)


def tilted(theta, axis=1):
    """A unit quaternion turned by ``theta`` about a body axis: the body x axis horizontal (``axis = 1``,
    exact zeros: ``L_z`` is exactly 0 for ``omega0`` along x) or the y axis (``axis = 2``)."""
    q = np.zeros(4)
    q[0], q[axis] = np.cos(theta / 2), np.sin(theta / 2)
    return q


def euler_swing(phi, theta, psi, rate):
    """A planar swing from 3-1-3 angles (``q0`` by :func:`rigidjax.quat_from_euler`, whose rounding
    leaves ``L_z / I1`` at ~1e-16 rad/s instead of 0): ``omega0 = theta' (cos psi, -sin psi, 0)``."""
    q0 = np.asarray(rj.quat_from_euler(jnp.array([phi, theta, psi])))
    return rate * np.array([np.cos(psi), -np.sin(psi), 0.0]), q0


CASES = {
    "rest_tilt": (np.zeros(3), tilted(0.2), 1.0),
    "rest_tilt_y": (np.zeros(3), tilted(0.3, axis=2), 0.6),
    "planar_swing": (np.array([1.5, 0.0, 0.0]), tilted(0.4), 1.3),
    "planar_over_the_top": (np.array([12.0, 0.0, 0.0]), tilted(0.4), 0.9),
    "hanging_at_rest": (np.zeros(3), np.array([np.cos(np.pi / 2), 1.0, 0.0, 0.0]), 0.5),
    # Started exactly at a pole with a wobble: the tilt of q0 moves b + k a off 0.
    "upright_wobble": (np.array([1.0, 0.5, 3.0]), np.array([1.0, 0.0, 0.0, 0.0]), 0.8),
    "hanging_wobble": (np.array([1.0, 0.5, 3.0]), np.array([0.0, 1.0, 0.0, 0.0]), 0.8),
    # At a pole up to the rounding of q0 (cos(pi / 2) = 6e-17, as from Euler angles), spinning.
    "hanging_spinning_rounded": (
        np.array([0.0, 0.0, 30.0]),
        np.array([np.cos(np.pi / 2), 1.0, 0.0, 0.0]),
        1.0,
    ),
    "hanging_fast_rounded": (np.array([0.0, 0.0, 300.0]), np.array([np.cos(np.pi / 2), 1.0, 0.0, 0.0]), 0.1),
    "planar_swing_rounded": (*euler_swing(0.3, 0.4, 0.7, 1.5), 1.3),
    "planar_over_the_top_rounded": (*euler_swing(1.1, 0.4, -0.4, 12.0), 0.9),
    "upright_wobble_rounded": (np.array([1.0, 0.5, 3.0]), np.array([1.0, 0.0, 1e-17, 0.0]), 0.8),
}


@pytest.fixture(scope="module", params=list(CASES))
def case(request):
    omega0, q0, t = CASES[request.param]
    return omega0, q0, t, reference_jacobian(omega0, q0, t)


def test_jacfwd(case):
    omega0, q0, t, expected = case
    jacobian, value = _jacfwd(jnp.asarray(omega0), NO_TILT, jnp.asarray(q0), t)
    np.testing.assert_allclose(np.asarray(value), reference(omega0, q0, t), rtol=0, atol=1e-10)
    jacobian = np.concatenate([np.asarray(j) for j in jacobian], axis=1)
    assert np.all(np.isfinite(jacobian))
    np.testing.assert_allclose(jacobian, expected, rtol=0, atol=1e-6 * np.max(np.abs(expected)))


def test_grad(case):
    omega0, q0, t, expected = case
    gradient = np.concatenate(
        [np.asarray(g) for g in _grad(jnp.asarray(omega0), NO_TILT, jnp.asarray(q0), t)]
    )
    assert np.all(np.isfinite(gradient))
    np.testing.assert_allclose(gradient, WEIGHTS @ expected, rtol=0, atol=1e-6 * np.max(np.abs(expected)))
