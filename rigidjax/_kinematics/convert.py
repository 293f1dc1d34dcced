"""Converters between rigidjax's orientations and states and those of scipy and MuJoCo.

rigidjax: unit quaternions scalar first ``(w, x, y, z)``, mapping body-frame to space-frame
components; ``omega`` in body-frame components (rad/s). scipy's ``Rotation`` stores the same
rotation scalar LAST ``(x, y, z, w)``. A MuJoCo free joint's ``qpos`` is ``(x, y, z, qw, qx, qy,
qz)``: the position of the body frame's origin in the world, then the same scalar-first
body-to-world quaternion as rigidjax's; its ``qvel`` is ``(vx, vy, vz, wx, wy, wz)``: the linear
velocity in world components, then the angular velocity in BODY components, as rigidjax's ``omega``.
"""

import jax.numpy as jnp
import numpy as np

from .._checks import (
    check_batch_shapes,
    check_finite,
    check_last_axis,
    common_float,
    compiled_when_eager,
    error_if,
    unit_tolerance,
)
from .._dynamics.state import State

__all__ = [
    "from_mujoco_free_joint",
    "from_scipy_rotation",
    "quat_from_scalar_last",
    "quat_to_scalar_last",
    "to_mujoco_free_joint",
    "to_scipy_rotation",
]

# (w, x, y, z) -> (x, y, z, w) and back.
_TO_LAST = np.array([1, 2, 3, 0])
_TO_FIRST = np.array([3, 0, 1, 2])


def _not_unit_message(name: str, where: str, tol: float) -> str:
    return (
        f"{where}: {name} is not a unit quaternion (| |q| - 1 | > {tol:g}); normalise it "
        "(rigidjax.quat_normalize) or build it with quat_from_euler / quat_from_matrix."
    )


def _check_unit(q, name: str, where: str):
    """``q`` wrapped in run-time checks (finite, ``| |q| - 1 |`` within ``unit_tolerance``) and NOT
    divided by its norm: the converters move numbers, so that round trips are exact."""
    q = check_finite(q, name, where)
    tol = unit_tolerance(q.dtype)
    off = jnp.abs(jnp.linalg.norm(q, axis=-1) - 1.0)
    return error_if(q, off > tol, _not_unit_message(name, where, tol))


def _unit(q, name: str, where: str):
    (q,) = common_float(q, names=[name])
    check_last_axis(q, 4, name)
    return _check_unit(q, name, where)


@compiled_when_eager
def quat_to_scalar_last(q):
    """Reorder a rigidjax quaternion ``(w, x, y, z)`` to the scalar-last ``(x, y, z, w)`` order of
    scipy, Eigen's coefficients, ROS and most game engines.

    The rotation is unchanged: only the order of the components. Works under ``jax.jit`` and
    ``jax.vmap``; the dtype (float32 or float64) is kept.

    **Arguments:**

    - `q`: unit quaternion(s), scalar first ``(w, x, y, z)``, shape ``(..., 4)``, body -> space.

    **Returns:** the same quaternion(s), scalar last ``(x, y, z, w)``, shape ``(..., 4)``: the same
    numbers, reordered (so a round trip is exact). A last axis other than 4 raises ``ValueError``; NaN or
    inf, or a norm off 1 by more than ``1e-6`` (float64) / ``1e-4`` (float32), raises at run time
    (``ValueError``; ``EquinoxRuntimeError`` inside ``jit``), naming `q`.
    """
    return _unit(q, "q", "quat_to_scalar_last")[..., _TO_LAST]


@compiled_when_eager
def quat_from_scalar_last(q):
    """Reorder a scalar-last quaternion ``(x, y, z, w)`` (scipy, Eigen's coefficients, ROS) to
    rigidjax's scalar-first ``(w, x, y, z)``.

    Works under ``jax.jit`` and ``jax.vmap``; the dtype (float32 or float64) is kept.

    **Arguments:**

    - `q`: unit quaternion(s), scalar last ``(x, y, z, w)``, shape ``(..., 4)``, body -> space.

    **Returns:** the same quaternion(s), scalar first ``(w, x, y, z)``, shape ``(..., 4)``: the same
    numbers, reordered. A last axis other than 4 raises ``ValueError``; NaN or inf, or a norm off 1 by
    more than ``1e-6`` (float64) / ``1e-4`` (float32), raises at run time, naming `q`.
    """
    return _unit(q, "q", "quat_from_scalar_last")[..., _TO_FIRST]


def _scipy_rotation_class():
    try:
        from scipy.spatial.transform import Rotation
    except ImportError as error:  # pragma: no cover - depends on the environment
        raise ImportError(
            "rigidjax.convert's scipy converters need scipy: pip install scipy (>= 1.11)."
        ) from error
    return Rotation


def to_scipy_rotation(q):
    """A ``scipy.spatial.transform.Rotation`` of rigidjax quaternion(s).

    scipy's quaternions are scalar last; this reorders them. The rotation (body -> space, so
    ``rotation.apply(v_body)`` is ``rigidjax.quat_rotate(q, v_body)``) and its matrix are those of
    rigidjax. scipy is imported when this is called, not with ``rigidjax``. Not for use inside
    ``jax.jit`` (the result is a scipy object).

    **Arguments:**

    - `q`: unit quaternion(s), scalar first ``(w, x, y, z)``, shape ``(4,)`` or ``(..., 4)``. More
      than one leading axis needs a scipy whose ``Rotation`` has N-D shapes (1.16 and later).

    **Returns:** a ``Rotation``: a single one for ``q`` of shape ``(4,)``, otherwise one of shape
    ``q.shape[:-1]``. Its quaternions equal ``q`` (same sign) up to roundoff.

    Raises ``ValueError`` naming `q` for a last axis other than 4, NaN or inf, or a norm off 1 by
    more than ``1e-6`` (float64) / ``1e-4`` (float32); ``ImportError`` without scipy.
    """
    Rotation = _scipy_rotation_class()
    q = np.asarray(q)
    if not np.issubdtype(q.dtype, np.floating) and not np.issubdtype(q.dtype, np.integer):
        raise TypeError(f"to_scipy_rotation: q must be a real number array, got dtype {q.dtype}.")
    q = q.astype(np.float64 if q.dtype != np.float32 else np.float32)
    check_last_axis(q, 4, "q")
    if not np.all(np.isfinite(q)):
        raise ValueError("to_scipy_rotation: q contains NaN or inf.")
    tol = unit_tolerance(q.dtype)
    if np.any(np.abs(np.linalg.norm(q, axis=-1) - 1.0) > tol):
        raise ValueError(_not_unit_message("q", "to_scipy_rotation", tol))
    try:
        return Rotation.from_quat(q[..., _TO_LAST].astype(np.float64))
    except ValueError as error:
        if q.ndim <= 2:
            raise
        raise ValueError(
            f"to_scipy_rotation: this scipy's Rotation takes shape (4,) or (N, 4), got q of shape "
            f"{q.shape}; pass q.reshape(-1, 4), or update scipy (N-D rotations: 1.16 and later)."
        ) from error


def from_scipy_rotation(rotation, dtype=None):
    """rigidjax quaternion(s) of a ``scipy.spatial.transform.Rotation``.

    The inverse of :func:`to_scipy_rotation`: scipy's scalar-last quaternions reordered to
    ``(w, x, y, z)``, with the sign scipy stores (no canonical sign is imposed).

    **Arguments:**

    - `rotation`: a scipy ``Rotation``, single or of any shape.
    - `dtype`: the float dtype of the result; default JAX's default float (float64 with
      ``jax_enable_x64``, float32 otherwise).

    **Returns:** unit quaternion(s) ``(w, x, y, z)`` (body -> space), shape ``(4,)`` for a single
    rotation, ``rotation.shape + (4,)`` otherwise. A ``TypeError`` for anything but a ``Rotation``.
    """
    Rotation = _scipy_rotation_class()
    if not isinstance(rotation, Rotation):
        raise TypeError(
            f"from_scipy_rotation: rotation must be a scipy.spatial.transform.Rotation, got "
            f"{type(rotation).__name__}."
        )
    q = np.asarray(rotation.as_quat())[..., _TO_FIRST]
    dtype = jnp.result_type(float) if dtype is None else jnp.dtype(dtype)
    if not jnp.issubdtype(dtype, jnp.floating):
        raise TypeError(f"from_scipy_rotation: dtype must be a float dtype, got {dtype}.")
    return jnp.asarray(q, dtype)


def _vector(x, size: int, name: str):
    (x,) = common_float(x, names=[name])
    check_last_axis(x, size, name)
    return x


@compiled_when_eager
def to_mujoco_free_joint(state: State, position=None, velocity=None):
    """MuJoCo free-joint coordinates ``(qpos, qvel)`` of a rigidjax state.

    MuJoCo's free joint has ``qpos = (x, y, z, qw, qx, qy, qz)``: the world position of the body
    frame's origin, then a scalar-first unit quaternion mapping body to world components (rigidjax's
    convention), and ``qvel = (vx, vy, vz, wx, wy, wz)``: the origin's linear velocity in WORLD
    components, then the angular velocity in BODY components (rigidjax's ``omega``). rigidjax's motion
    is about the centre of mass: it is the MuJoCo body's when the body's inertial frame sits at its
    origin along its axes (``<inertial pos="0 0 0" diaginertia="I1 I2 I3" .../>``).

    Works under ``jax.jit`` and ``jax.vmap``; the arrays broadcast against each other.

    **Arguments:**

    - `state`: a :class:`rigidjax.State` with an orientation (``omega`` ``(..., 3)`` rad/s, body frame;
      ``orientation`` ``(..., 4)``, scalar first, body -> space).
    - `position`: world position (m) of the body, ``(..., 3)``; default the origin.
    - `velocity`: world linear velocity (m/s), ``(..., 3)``; default zero.

    **Returns:** ``(qpos, qvel)`` of shapes ``(..., 7)`` and ``(..., 6)``, in the state's dtype (the
    widest float of the inputs). For ``mujoco.MjData`` of one free body: ``data.qpos[:] = qpos``.

    A state without an orientation or wrong last-axis sizes raise ``ValueError`` naming the argument;
    NaN or inf, or a non-unit orientation, raise at run time (``ValueError``; ``EquinoxRuntimeError``
    inside ``jit``).
    """
    if not isinstance(state, State):
        raise TypeError(f"to_mujoco_free_joint: state must be a rigidjax.State, got {type(state).__name__}.")
    if state.orientation is None:
        raise ValueError(
            "to_mujoco_free_joint: state.orientation is None; a free joint needs the orientation "
            "(rigidjax.State(omega, orientation))."
        )
    where = "to_mujoco_free_joint"
    zeros = jnp.zeros(3, state.omega.dtype)
    position = zeros if position is None else position
    velocity = zeros if velocity is None else velocity
    omega, q, position, velocity = common_float(
        state.omega,
        state.orientation,
        position,
        velocity,
        names=["state.omega", "state.orientation", "position", "velocity"],
    )
    for x, size, name in [
        (omega, 3, "state.omega"),
        (q, 4, "state.orientation"),
        (position, 3, "position"),
        (velocity, 3, "velocity"),
    ]:
        check_last_axis(x, size, name)
    batch = check_batch_shapes(
        where,
        ("state.omega", omega, 1),
        ("state.orientation", q, 1),
        ("position", position, 1),
        ("velocity", velocity, 1),
    )
    q = _check_unit(q, "state.orientation", where)
    omega = check_finite(omega, "state.omega", where)
    position = check_finite(position, "position", where)
    velocity = check_finite(velocity, "velocity", where)

    def full(x):
        return jnp.broadcast_to(x, batch + x.shape[-1:])

    qpos = jnp.concatenate([full(position), full(q)], axis=-1)
    qvel = jnp.concatenate([full(velocity), full(omega)], axis=-1)
    return qpos, qvel


@compiled_when_eager
def from_mujoco_free_joint(qpos, qvel):
    """A rigidjax state, position and linear velocity of MuJoCo free-joint coordinates.

    The inverse of :func:`to_mujoco_free_joint`: ``qpos = (x, y, z, qw, qx, qy, qz)`` (world
    position of the body frame's origin, scalar-first body -> world quaternion) and
    ``qvel = (vx, vy, vz, wx, wy, wz)`` (world linear velocity, BODY-frame angular velocity). Works
    under ``jax.jit`` and ``jax.vmap``.

    **Arguments:**

    - `qpos`: ``(..., 7)``, e.g. ``data.qpos`` of a model with one free body, or the slice
      ``data.qpos[model.jnt_qposadr[j]:][:7]`` of free joint ``j``.
    - `qvel`: ``(..., 6)``, e.g. ``data.qvel[model.jnt_dofadr[j]:][:6]``; broadcast against `qpos`.

    **Returns:** ``(state, position, velocity)``: a :class:`rigidjax.State` (``omega`` ``(..., 3)``
    body frame, rad/s; ``orientation`` ``(..., 4)``, the numbers of `qpos`), the world position ``(...,
    3)`` (m) and the world linear velocity ``(..., 3)`` (m/s), in the wider dtype of the inputs.

    Wrong last-axis sizes raise ``ValueError`` naming the argument; NaN or inf, or a quaternion whose
    norm is off 1 by more than ``1e-6`` (float64) / ``1e-4`` (float32), raise at run time
    (``ValueError``; ``EquinoxRuntimeError`` inside ``jit``).
    """
    where = "from_mujoco_free_joint"
    qpos, qvel = common_float(qpos, qvel, names=["qpos", "qvel"])
    check_last_axis(qpos, 7, "qpos")
    check_last_axis(qvel, 6, "qvel")
    batch = check_batch_shapes(where, ("qpos", qpos, 1), ("qvel", qvel, 1))
    qpos = jnp.broadcast_to(check_finite(qpos, "qpos", where), batch + (7,))
    qvel = jnp.broadcast_to(check_finite(qvel, "qvel", where), batch + (6,))
    q = _check_unit(qpos[..., 3:], "qpos[..., 3:7] (the quaternion)", where)
    return State(qvel[..., 3:], q), qpos[..., :3], qvel[..., :3]
