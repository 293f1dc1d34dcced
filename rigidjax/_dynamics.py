"""Euler's equations and the dynamical quantities of a rotating rigid body.

Everything is in the body frame, where the inertia tensor is constant. ``inertia`` is principal
moments ``(..., 3)`` (body axes are principal axes) or a full symmetric tensor ``(..., 3, 3)``: a
trailing ``(3, 3)`` is always read as a tensor.
"""

import jax.numpy as jnp

from ._misc import check_last_axis, common_float
from ._quaternion import quat_rotate
from ._types import Inertia, Quaternion, Scalar, ScalarOut, Vector, VectorOut


def is_full_tensor(inertia, name: str = "inertia") -> bool:
    """True when ``inertia`` is a ``(..., 3, 3)`` tensor, False for principal moments ``(..., 3)``;
    a ``ValueError`` naming ``name`` for any other shape."""
    shape = jnp.shape(inertia)
    if len(shape) >= 2 and shape[-2:] == (3, 3):
        return True
    if len(shape) >= 1 and shape[-1] == 3:
        return False
    raise ValueError(
        f"{name} must be principal moments of shape (..., 3) or a tensor of shape (..., 3, 3) "
        f"(kg m^2), got shape {tuple(shape)}."
    )


def inertia_times(inertia: Inertia, omega: Vector) -> VectorOut:
    """``I @ omega`` for principal moments or a full tensor."""
    inertia, omega = common_float(inertia, omega, names=["inertia", "omega"])
    check_last_axis(omega, 3, "omega")
    if is_full_tensor(inertia):
        return jnp.einsum("...ij,...j->...i", inertia, omega)
    return inertia * omega


def euler_equations(inertia: Inertia, omega: Vector, torque: Vector | None = None) -> VectorOut:
    """Angular acceleration ``d(omega)/dt`` in the body frame (rad/s^2).

    Principal moments: ``I1 w1' = (I2 - I3) w2 w3 + tau1`` and cyclic. Full tensor:
    ``I w' = tau - w x (I w)``, solved for ``w'``. ``torque`` is in body-frame components (N m).
    """
    if torque is None:
        inertia, omega = common_float(inertia, omega, names=["inertia", "omega"])
        torque = jnp.zeros((), omega.dtype)
    else:
        inertia, omega, torque = common_float(inertia, omega, torque, names=["inertia", "omega", "torque"])
        check_last_axis(torque, 3, "torque")
    check_last_axis(omega, 3, "omega")
    if is_full_tensor(inertia):
        L = jnp.einsum("...ij,...j->...i", inertia, omega)
        rhs = torque - jnp.cross(omega, L)
        rhs, inertia = jnp.broadcast_arrays(rhs, inertia[..., 0])[0], inertia
        batch = jnp.broadcast_shapes(rhs.shape[:-1], inertia.shape[:-2])
        return jnp.linalg.solve(
            jnp.broadcast_to(inertia, batch + (3, 3)), jnp.broadcast_to(rhs, batch + (3,))[..., None]
        )[..., 0]
    I1, I2, I3 = inertia[..., 0], inertia[..., 1], inertia[..., 2]
    w1, w2, w3 = omega[..., 0], omega[..., 1], omega[..., 2]
    gyro = jnp.stack([(I2 - I3) * w2 * w3, (I3 - I1) * w3 * w1, (I1 - I2) * w1 * w2], axis=-1)
    return (gyro + torque) / inertia


def angular_momentum(inertia: Inertia, omega: Vector) -> VectorOut:
    """Angular momentum ``L = I omega`` in body-frame components (kg m^2/s)."""
    return inertia_times(inertia, omega)


def space_angular_momentum(inertia: Inertia, omega: Vector, orientation: Quaternion) -> VectorOut:
    """Angular momentum in space-frame components, ``R L_body``; conserved when torque-free."""
    L = inertia_times(inertia, omega)
    orientation = jnp.asarray(orientation, L.dtype)
    check_last_axis(orientation, 4, "orientation")  # name the caller's argument, not quat_rotate's q
    return quat_rotate(orientation, L)


def kinetic_energy(inertia: Inertia, omega: Vector) -> ScalarOut:
    """Rotational kinetic energy ``omega . (I omega) / 2`` (J)."""
    L = inertia_times(inertia, omega)
    return 0.5 * jnp.sum(jnp.asarray(omega, L.dtype) * L, axis=-1)


def free_precession_rate(I1: Scalar, I3: Scalar, omega3: Scalar) -> ScalarOut:
    """Body-frame free precession rate ``(I3 - I1) / I1 * omega3`` of a torque-free symmetric top.

    ``I1 = I2`` are the transverse moments and ``I3`` the symmetry-axis moment. The transverse
    angular velocity turns about the body symmetry axis as ``w1 + i w2 = A exp(i Omega t)``, so a
    prolate body (``I3 < I1``) precesses backwards. For the Earth this is the Euler wobble rate.
    """
    I1, I3, omega3 = common_float(I1, I3, omega3, names=["I1", "I3", "omega3"])
    return (I3 - I1) / I1 * omega3
